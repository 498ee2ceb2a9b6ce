"""osmo's built-in robotics task types, installed with osmo.

They are registered as ``osmo.task_types`` entry points: ``sim.rollout``, ``sim.eval``,
``lerobot.dataset``, ``lerobot.train`` and ``viz.rerun``.

Each entry-point module declares a :class:`osmo_plugins._base.PluginType` and imports nothing
heavy; the work lives in private modules (``_rollout``, ``_eval``, ...) that import numpy,
gymnasium/mujoco, torch/lerobot or rerun when the task runs. The MCAP episode format every
type shares is :mod:`osmo_plugins.episodes`.
"""
