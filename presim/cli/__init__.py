"""``presim`` command line. Each sub-module registers its sub-commands (one-line help each)."""

from __future__ import annotations

import argparse
import errno
import importlib
import re
import signal
import sys
import threading
from pathlib import Path

from presim import runtime

# Order = order in `presim --help`, following the data flow.
_MODULES = [
    "presim.cli.sample_cmd",      # sample-scene
    "presim.cli.capture_cmds",    # import, info
    "presim.cli.align_cmds",      # align, eval-poses
    "presim.cli.refine_eval_cmds",  # refine, complete, eval-views
    "presim.cli.photometric_cmd",  # photometric
    "presim.cli.render_cmd",      # render
    "presim.cli.sim_cmds",        # drive
    "presim.cli.teleop_cmd",      # teleop
    "presim.cli.outputs_cmds",    # ros
    "presim.cli.recover_cmd",     # recover
    "presim.cli.ros2_cmd",        # ros2
    "presim.cli.objects_cmd",     # objects, gen-bop-real
    "presim.cli.dataset_cmds",    # gen-bop
    "presim.cli.pose_cmds",       # pose-eval
    "presim.cli.posenet_cmds",    # pose-train, pose-predict
    "presim.cli.sim2real_cmd",    # sim2real depth
    "presim.cli.demo_cmd",        # demo
]


class HelpFormatter(argparse.HelpFormatter):
    """The one help style of every command: each option's default as ``(default: X)``.

    A default the help text does not state is appended; one it states as ``(default X`` /
    ``; default X`` is written ``default: X``. tests/test_cli_help.py checks the rules on every command.
    """

    def _get_help_string(self, action):
        h = _DEFAULT_WORDS.sub(r"\1default: ", action.help or "")
        if ("%(default)" in h or re.search(r"\bdefault\b", h) or action.default is None or action.default is False
                or action.default is argparse.SUPPRESS or not action.option_strings):
            return h
        return h + " (default: %(default)s)"


# "(default 60)", "; default 0)", ", default 0.015 m" -> "default: ..." (not "'default'", "the default robot")
_DEFAULT_WORDS = re.compile(r"([(;,] ?)default (?=[^\s(])")

COMMON_OPTIONS_HELP = (
    "common options of every command:\n"
    "  --max-memory SIZE  memory the command may plan to use, e.g. 16G (default: half of the memory available\n"
    "                     at start, or $PRESIM_MAX_MEMORY); a command whose sizes need more refuses to start\n"
    "  --quiet            no progress bars (they are also off when stderr is not a terminal)")


SCENE_WRITERS = ("refine", "complete", "fuse", "align", "photometric", "objects")
"""Commands that write into the scene folder they are given (argument ``scene``): each holds the
folder's lock (:func:`presim.io_utils.folder_lock`) while it runs."""


def _add_common_options(p: argparse.ArgumentParser, name: str = "") -> None:
    """The shared options, one short line each (the full text: COMMON_OPTIONS_HELP, in `presim --help`)."""
    p.formatter_class = HelpFormatter
    if name in SCENE_WRITERS or name == "gen-bop":
        p.add_argument("--no-wait", action="store_true",
                       help="when another command is writing into the same folder, stop with an error naming "
                            "it instead of waiting for it")
    nested = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
    for a in nested:  # e.g. `presim sim2real depth`: the options belong to the leaf commands
        for q in a.choices.values():
            _add_common_options(q, name)
    if nested:
        return
    g = p.add_argument_group("common options (see `presim --help`)")
    g.add_argument("--max-memory", default=None, metavar="SIZE", help="memory budget, e.g. 16G")
    g.add_argument("--quiet", action="store_true", help="no progress bars")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="presim",
        description="PreSim: photo-realistic RGB-D robot simulator built from captured RGB-D images.",
        epilog=COMMON_OPTIONS_HELP, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    from presim import __version__

    parser.add_argument("--version", action="version", version=f"presim {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", title="commands")
    for name in _MODULES:
        importlib.import_module(name).register(sub)
    for name, p in sub.choices.items():
        _add_common_options(p, name)
    return parser


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    # First: libgomp reads OMP_WAIT_POLICY once, when a command's first torch import or numba
    # parallel kernel loads it (presim/runtime.py).
    runtime.configure()
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    in_main = threading.current_thread() is threading.main_thread()
    if in_main:
        # SIGTERM (kill, roslaunch shutdown, a scheduler's stop) ends a command like Ctrl-C: the
        # writers' finally blocks close and rename their files instead of leaving *.partial.
        old_term = signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        return _run(args)
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, old_term)


def _call(args: argparse.Namespace) -> int:
    scene = getattr(args, "scene", None)
    if args.command in SCENE_WRITERS and scene is not None and Path(scene).is_dir():
        from presim.io_utils import folder_lock

        with folder_lock(scene, f"presim {args.command}", wait=not args.no_wait):
            return int(args.func(args) or 0)
    return int(args.func(args) or 0)


def _run(args: argparse.Namespace) -> int:
    if getattr(args, "quiet", False):
        from presim.io_utils import set_progress

        set_progress(False)
    try:
        return _call(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except (OSError, ValueError, MemoryError) as e:
        # Bad input (missing / unreadable / wrong kind of file, bad values): one clear line naming
        # the file and the problem, no traceback.
        msg = str(e) if not isinstance(e, MemoryError) else f"out of memory ({e or 'allocation failed'})"
        if isinstance(e, OSError) and e.errno == errno.ENOSPC and type(e) is OSError:
            # a write that found the disk full: the path, not the bare errno
            msg = f"{e.filename or 'output'}: no space left on device"
        print(f"presim {args.command}: error: {msg}", file=sys.stderr)
        return 1
    except ImportError as e:
        # An optional dependency group is not installed (scripts/setup.sh installs all of them).
        print(f"presim {args.command}: error: {e}; install the optional dependencies with "
              "`pip install -e .[all]` (or run scripts/setup.sh)", file=sys.stderr)
        return 1
