"""The public API (presim/api/, docs/api.md) on the small toy room: poses in every accepted form,
the scene's own intrinsics list, scaled sizes, the simulator and the Gymnasium env from one scene,
and a light ``import presim``."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import presim
from presim.api import as_intrinsics, as_pose
from presim.capture.store import save_scene
from presim.geometry import pose_to_tum
from presim.testing.toy_scene import ToyRoomConfig, build_toy_room


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    path = save_scene(build_toy_room(ToyRoomConfig(width=64, height=48)), tmp_path_factory.mktemp("toy") / "toy")
    return presim.open_scene(path)


def test_import_presim_is_light():
    code = "import sys, presim; print(sorted(m for m in ('numba', 'cv2', 'presim.api') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
    assert {"open_scene", "Scene", "Simulator"} <= set(dir(presim))
    with pytest.raises(AttributeError):
        presim.no_such_name  # noqa: B018


def test_pose_forms_agree(scene):
    T = scene.T_world_cam[1]
    tum = pose_to_tum(T)
    for form in (T, tum, (tum[:3], tum[3:]), (list(tum[:3]), list(tum[3:]))):
        np.testing.assert_allclose(as_pose(form), T, atol=1e-9)
    for bad in (np.eye(3), (np.zeros(3), np.zeros(3)), np.zeros(6)):
        with pytest.raises(ValueError):
            as_pose(bad)


def test_render_takes_the_scenes_intrinsics(scene):
    T = scene.T_world_cam[0]
    a = scene.render(T)
    b = scene.render(T, K=scene.intrinsics)  # the list a user finds on the scene
    c = scene.render(T, K=scene.intrinsics[0])
    assert a.color.shape == (48, 64, 3) and a.depth_m.dtype == np.float32
    np.testing.assert_array_equal(a.color, b.color)
    np.testing.assert_array_equal(b.depth_m, c.depth_m)
    small = scene.render(T, size=(32, 24))
    assert small.color.shape == (24, 32, 3) and small.valid.mean() > 0.5
    assert as_intrinsics(scene.intrinsics) is scene.intrinsics[0]
    with pytest.raises(ValueError, match="Intrinsics"):
        as_intrinsics([[500.0, 500.0]])
    with pytest.raises(ValueError, match="size"):
        scene.render(T, size=(0, 24))


def test_simulator_and_gym_env_take_the_scene(scene):
    import gymnasium

    sim = presim.Simulator(scene, robot="default", size=(32, 24))
    r = sim.reset(seed=0)
    r = sim.step([0.2, 0.0, 0.1])
    assert r.cameras[0].color.shape == (24, 32, 3) and sim.robot.urdf_path.name == "presim_bot.urdf"
    sim.close()
    env = gymnasium.make("PreSim-PointNav-v0", scene=scene, width=32, height=24)
    obs, _ = env.reset(seed=0)
    assert obs["rgb"].shape == (24, 32, 3)
    env.close()
