"""What ``sim.eval`` reports: success defined per env, confidence intervals, normalised scores.

Success is decided per env, never guessed (an episode that merely did not terminate says
nothing on HalfCheetah, which never terminates). In order:

1. the env's own signal: ``info["is_success"]`` or ``info["success"]`` (an episode succeeds
   when any of its steps reports it);
2. a return threshold (success: return ≥ X): the workflow's ``success: {ENV: {return_at_least:
   X}}``, else its ``success: {return_at_least: X}``, else gymnasium's ``reward_threshold`` —
   which is defined over the env's registered episode length, so it applies only when the
   suite runs exactly that many steps;
3. otherwise there is no success rate: ``None`` (shown as ``n/a``), with the reason.

The normalised score puts policies on one scale across envs: ``(return - random) / (expert -
random)``, from the random and expert rows of the same suite (0 = random, 1 = expert).

Pure logic over :class:`~osmo_plugins.sim.envs.EpisodeResult` lists; gymnasium is imported
only to read an env's registered ``reward_threshold``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from osmo_plugins.sim.envs import EpisodeResult

__all__ = ["Criterion", "add_normalized", "choose_criterion", "ci95", "parse_success",
           "summarize"]

RETURN_KEY = "return_at_least"

# Two-sided 95% Student t quantiles for 1..30 degrees of freedom; normal beyond.
_T95 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179,
        2.160, 2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064,
        2.060, 2.056, 2.052, 2.048, 2.045, 2.042)


def ci95(values: Sequence[float]) -> tuple[float, float]:
    """The 95% confidence interval of the mean (Student t; a point for one value)."""
    n = len(values)
    mean = sum(values) / n
    if n < 2:
        return mean, mean
    sd = math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1))
    half = (_T95[n - 2] if n - 1 <= len(_T95) else 1.96) * sd / math.sqrt(n)
    return mean - half, mean + half


@dataclass(frozen=True)
class Criterion:
    """How success was decided on one env.

    Attributes:
        kind: ``signal`` (the env's info key), ``return`` (a threshold) or ``none``.
        description: one line for people (``osmo eval report`` shows it).
        key: the info key for ``signal``.
        threshold: the return threshold for ``return``.
        source: where the threshold came from (``params``, ``params[ENV]``, ``gymnasium``).
    """

    kind: str
    description: str
    key: str | None = None
    threshold: float | None = None
    source: str | None = None

    def success_rate(self, results: Sequence[EpisodeResult]) -> float | None:
        """The fraction of episodes that succeeded, or None without a criterion."""
        if self.kind == "signal":
            return sum(1 for r in results if r.success) / len(results)
        if self.kind == "return" and self.threshold is not None:
            return sum(1 for r in results if r.total_reward >= self.threshold) / len(results)
        return None

    def to_json(self) -> dict[str, Any]:
        """The ``metrics.json`` form."""
        return {"kind": self.kind, "description": self.description, "key": self.key,
                "threshold": self.threshold, "source": self.source}


def parse_success(value: Mapping[str, Any], envs: Sequence[str]
                  ) -> tuple[float | None, dict[str, float]]:
    """The ``success`` param → (threshold for every env, thresholds per env).

    Accepts ``{return_at_least: X}`` and ``{ENV_ID: {return_at_least: X}}`` for env ids of
    the suite, mixed. Raises ValueError naming every problem at once.
    """
    default: float | None = None
    per_env: dict[str, float] = {}
    problems: list[str] = []

    def number(v: Any, where: str) -> float | None:
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            problems.append(f"{where} must be a number, got {v!r}")
            return None
        return float(v)

    for key, v in value.items():
        if key == RETURN_KEY:
            default = number(v, f"success.{RETURN_KEY}")
        elif key in envs:
            if not isinstance(v, Mapping) or set(v) != {RETURN_KEY}:
                problems.append(f"success.{key} must be {{{RETURN_KEY}: NUMBER}}, got {v!r}")
                continue
            found = number(v[RETURN_KEY], f"success.{key}.{RETURN_KEY}")
            if found is not None:
                per_env[key] = found
        else:
            problems.append(f"success has unknown key {key!r}: use {RETURN_KEY} or one of the "
                            f"suite's envs ({', '.join(envs)})")
    if problems:
        raise ValueError("; ".join(problems))
    return default, per_env


def _gym_threshold(env_id: str, max_steps: int) -> tuple[float | None, str]:
    """Gymnasium's ``reward_threshold`` when it applies to ``max_steps``-step episodes."""
    try:
        import gymnasium

        spec = gymnasium.spec(env_id)
    except Exception:  # noqa: BLE001 - an unregistered or broken spec: no threshold to use
        return None, "no registered gymnasium spec"
    if spec.reward_threshold is None:
        return None, "gymnasium defines no reward_threshold"
    if spec.max_episode_steps != max_steps:
        return None, (f"gymnasium's reward_threshold {spec.reward_threshold:g} is for "
                      f"{spec.max_episode_steps}-step episodes; this suite runs {max_steps}")
    return float(spec.reward_threshold), ""


def choose_criterion(env_id: str, results: Sequence[EpisodeResult], *, max_steps: int,
                     default: float | None = None,
                     per_env: Mapping[str, float] | None = None) -> Criterion:
    """Decide how success is measured on ``env_id`` (see the module docstring for the order).

    Args:
        env_id: the gymnasium id of the env.
        results: every episode of every policy on this env (an env signal shows up here).
        max_steps: the suite's episode step limit.
        default: the workflow's threshold for every env (:func:`parse_success`).
        per_env: the workflow's thresholds by env id.
    """
    keys = {r.signal for r in results if r.signal}
    if keys:
        key = sorted(keys)[0]
        return Criterion("signal", f"info[{key!r}] (the env's own success signal)", key=key)
    for threshold, source in (((per_env or {}).get(env_id), f"params[{env_id}]"),
                              (default, "params")):
        if threshold is not None:
            return Criterion("return", f"return >= {threshold:g} (workflow {source})",
                             threshold=threshold, source=source)
    threshold, why = _gym_threshold(env_id, max_steps)
    if threshold is not None:
        return Criterion("return", f"return >= {threshold:g} (gymnasium reward_threshold)",
                         threshold=threshold, source="gymnasium")
    return Criterion("none", f"n/a: no success signal and no return threshold ({why}; set "
                     f"success: {{{env_id}: {{{RETURN_KEY}: X}}}})")


def summarize(policy: str, kind: str, env_id: str, results: Sequence[EpisodeResult],
              criterion: Criterion) -> dict[str, Any]:
    """One row of ``metrics.json``: ``success_rate`` is None when there is no criterion."""
    returns = [r.total_reward for r in results]
    lo, hi = ci95(returns)
    return {
        "policy": policy, "kind": kind, "env": env_id, "episodes": len(results),
        "success_rate": criterion.success_rate(results),
        "success_criterion": criterion.description,
        "mean_return": sum(returns) / len(returns), "return_ci95": [lo, hi],
        "normalized_score": None, "normalized_ci95": None,
        "mean_length": sum(r.length for r in results) / len(results),
        "returns": returns, "seeds": [r.seed for r in results]}


def add_normalized(rows: list[dict[str, Any]]) -> None:
    """Fill ``normalized_score`` (and its interval) in place.

    Only for envs where both a random and an expert row ran and their mean returns differ.
    """
    base: dict[str, dict[str, float]] = {}
    for row in rows:
        if row["kind"] in ("random", "expert"):
            base.setdefault(row["env"], {})[row["kind"]] = row["mean_return"]
    for row in rows:
        ref = base.get(row["env"], {})
        if "random" not in ref or "expert" not in ref or ref["expert"] == ref["random"]:
            continue
        span = ref["expert"] - ref["random"]
        row["normalized_score"] = (row["mean_return"] - ref["random"]) / span
        lo, hi = ((v - ref["random"]) / span for v in row["return_ci95"])
        row["normalized_ci95"] = [min(lo, hi), max(lo, hi)]
