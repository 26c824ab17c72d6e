"""``presim`` command line. Each sub-module registers its sub-commands (one-line help each)."""

from __future__ import annotations

import argparse
import importlib
import signal
import sys
import threading

# Order = order in `presim --help`, following the data flow.
_MODULES = [
    "presim.cli.sample_cmd",      # sample-scene
    "presim.cli.capture_cmds",    # import, info
    "presim.cli.align_cmds",      # align, eval-poses
    "presim.cli.refine_eval_cmds",  # refine, eval-views
    "presim.cli.photometric_cmd",  # photometric
    "presim.cli.render_cmd",      # render
    "presim.cli.sim_cmds",        # drive
    "presim.cli.teleop_cmd",      # teleop
    "presim.cli.outputs_cmds",    # ros
    "presim.cli.ros2_cmd",        # ros2
    "presim.cli.objects_cmd",     # objects, gen-bop-real
    "presim.cli.dataset_cmds",    # gen-bop
    "presim.cli.pose_cmds",       # pose-eval
    "presim.cli.posenet_cmds",    # pose-train, pose-predict
    "presim.cli.sim2real_cmd",    # sim2real depth
    "presim.cli.demo_cmd",        # demo
]


class _HelpFormatter(argparse.HelpFormatter):
    """Shows each option's default, unless its help already says it or there is none to show."""

    def _get_help_string(self, action):
        h = action.help or ""
        if ("%(default)" in h or "default" in h or action.default in (None, False, argparse.SUPPRESS)
                or not action.option_strings):
            return h
        return h + " (default: %(default)s)"


def _add_common_options(p: argparse.ArgumentParser) -> None:
    p.formatter_class = _HelpFormatter
    if not any("--max-memory" in a.option_strings for a in p._actions):
        p.add_argument("--max-memory", default=None, metavar="SIZE",
                       help="memory the command may plan to use, e.g. 16G (default: half of the memory "
                            "available at start, or $PRESIM_MAX_MEMORY); commands whose sizes need more "
                            "refuse to start")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="presim",
        description="PreSim: photo-realistic RGB-D robot simulator built from captured RGB-D images.",
    )
    from presim import __version__

    parser.add_argument("--version", action="version", version=f"presim {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", title="commands")
    for name in _MODULES:
        importlib.import_module(name).register(sub)
    for p in sub.choices.values():
        _add_common_options(p)
    return parser


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
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


def _run(args: argparse.Namespace) -> int:
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except (OSError, ValueError, MemoryError) as e:
        # Bad input (missing / unreadable / wrong kind of file, bad values): one clear line naming
        # the file and the problem, no traceback.
        msg = str(e) if not isinstance(e, MemoryError) else f"out of memory ({e or 'allocation failed'})"
        print(f"presim {args.command}: error: {msg}", file=sys.stderr)
        return 1
    except ImportError as e:
        # An optional dependency group is not installed (scripts/setup.sh installs all of them).
        print(f"presim {args.command}: error: {e}; install the optional dependencies with "
              "`pip install -e .[all]` (or run scripts/setup.sh)", file=sys.stderr)
        return 1
