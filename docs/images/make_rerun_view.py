"""Regenerate the picture of an evaluation in the rerun viewer from a real run.

Runs ``workflows/reach-vision.yaml`` on tiny settings in a temporary ``OSMO_HOME`` (rollouts,
dataset, a few training steps, evaluation), converts its evaluation with ``osmo view`` and has
the rerun viewer take a screenshot of it without a window (``rerun --headless
--screenshot-to``).

    python docs/images/make_rerun_view.py           # from the repository root

Needs the ``sim``, ``learn`` and ``viz`` extras, and a Vulkan driver for the viewer: on a
machine without a GPU, Mesa's software one (Debian package ``mesa-vulkan-drivers``). Takes a
few minutes on 2 cores. Writes ``docs/images/rerun-eval.png``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
OUT = REPO / "docs" / "images" / "rerun-eval.png"
TINY = ["--set", "shards=2", "--set", "episodes=2", "--set", "steps=20",
        "--set", "eval_episodes=2"]


def _osmo(*args: str, env: dict[str, str]) -> str:
    proc = subprocess.run([sys.executable, "-m", "osmo", *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=1800)
    if proc.returncode != 0:
        raise SystemExit(f"osmo {' '.join(args)} exited {proc.returncode}\n{proc.stderr}")
    return proc.stdout


def main() -> None:
    """Run the workflow, convert its evaluation and take the viewer's screenshot."""
    rerun = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")
    if rerun is None:
        raise SystemExit('rerun is not installed: pip install -e ".[viz]"')
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, OSMO_HOME=str(Path(tmp) / "home"), OSMO_RUNTIME="process",
                   RERUN_ANALYTICS="0")
        env.pop("OSMO_SERVER", None)
        try:
            out = _osmo("submit", "workflows/reach-vision.yaml", "--wait", *TINY, env=env)
            wf_id = out.split("Workflow ID - ", 1)[1].split()[0]
            rrd = Path(tmp) / "eval.rrd"
            _osmo("view", f"{wf_id}:eval:eval.rrd", "--out", str(rrd), env=env)
        finally:
            _osmo("server", "stop", env=env)
        subprocess.run([rerun, "--headless", "--renderer", "vulkan", "--port", "0",
                        "--window-size", "1280x800", "--screenshot-to", str(OUT), str(rrd)],
                       env=env, check=True, timeout=300, capture_output=True)
    from PIL import Image  # installed with the learn extra (torchvision)

    with Image.open(OUT) as shot:  # the viewer renders at twice the window's size
        shot.resize((shot.width // 2, shot.height // 2), Image.Resampling.LANCZOS).save(
            OUT, optimize=True)
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
