"""Simulation task types: ``sim.rollout`` and ``sim.eval`` (gymnasium + MuJoCo; extra ``sim``)."""
