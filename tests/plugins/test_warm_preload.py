"""A built-in plugin warms its runner (``PluginType.warm``): its libraries imported once,
nothing decided for the runs that MuJoCo reads from the environment at import."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from tests.conftest import REPO

pytest.importorskip("mujoco")

PROBE = """
import json, os, sys
from osmo_plugins.sim.rollout import ROLLOUT
before = set(sys.modules)
ROLLOUT.warm()
seen = {"loaded": sorted(set(sys.modules) - before), "gl": os.environ.get("MUJOCO_GL"),
        "plugins": sys.modules["osmo_plugins"].__file__}
from osmo_plugins.sim.envs import make_env  # a render task after it: MUJOCO_GL=egl still works
env = make_env("InvertedPendulum-v5", render=True)
env.reset(seed=0)
seen["frame"] = list(env.render().shape)
print(json.dumps(seen))
"""


def test_the_rollout_type_warms_its_runner_without_choosing_a_gl_backend() -> None:
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), str(REPO / "plugins")])
    done = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True,
                          text=True, timeout=120, check=True, cwd=REPO)
    seen = json.loads(done.stdout.strip().splitlines()[-1])
    assert seen["plugins"].startswith(str(REPO)), seen["plugins"]
    loaded = set(seen["loaded"])
    assert {"gymnasium", "mujoco", "osmo_plugins.sim._rollout"} <= loaded, sorted(loaded)
    # what each run would import again in its fork: its env's module, the MCAP writer
    assert {"gymnasium.envs.mujoco.inverted_pendulum_v5", "foxglove.mcap",
            "osmo_plugins.foxglove_io"} <= loaded, sorted(loaded)
    assert seen["gl"] is None  # set only while importing, then gone
    assert not loaded & {"OpenGL", "mujoco.egl", "mujoco.osmesa"}, sorted(loaded)  # no backend
    assert seen["frame"] == [64, 64, 3]
