"""How well the loop itself held in one run, against the limits of its mode.

A run can reach its end with every vehicle verdict passing and still not be a valid test of
the controller: the plant drove most cycles on its fallback (the driver's torque split), the
controller refused most authenticators (a wrong SecOC key, SecOC on one side only), or, in a
realtime run, the loop missed its deadlines and its period jittered (a loaded machine). The
figures below come from the processes' summaries and the KPIs; :func:`loop_health` compares
them with the limits and names every one that was passed.

Limits (shares are of the run's communication cycles or authenticated frames):

* ``SECOC_REJECT_SHARE_MAX`` (1 %): SecOC rejections of either process over its accepted +
  rejected frames. A wrong key rejects every frame; a clean run rejects none.
* ``FALLBACK_SHARE_MAX`` (2 %): plant cycles on the fallback over all its cycles. A clean
  lockstep run has none; a lost controller or a SecOC mismatch has every cycle.
* realtime only (lockstep has no wall-clock deadline: the plant waits for every answer):
  ``DEADLINE_MISS_SHARE_MAX`` (1 %) turnarounds over the 10 ms period, and
  ``JITTER_P99_MAX_US`` (2 000 µs, a fifth of the 10 ms cycle) p99 period jitter.

Runs that inject faults, floods or rogue frames (``faults_injected``) are meant to make the
loop fall back or reject: their figures are reported, but they do not degrade the run.
"""

from __future__ import annotations

from typing import Any

from plant_sim.node import FALLBACK_SHARE_MAX, fallback_passed, fallback_text

__all__ = ["FALLBACK_SHARE_MAX"]  # the plant's own limit (plant_sim/node.py), used here too

SECOC_REJECT_SHARE_MAX = 0.01
DEADLINE_MISS_SHARE_MAX = 0.01
JITTER_P99_MAX_US = 2000.0
#: the reason a degraded run ends with (metrics.json ``reason``)
DEGRADED = "degraded"


def _secoc_share(summary: dict[str, Any]) -> float | None:
    """Rejected over accepted + rejected authenticated frames of one process (None: SecOC
    off or nothing received)."""
    secoc = summary.get("secoc") or {}
    if not secoc.get("enabled"):
        return None
    accepted = sum(int(v) for v in (secoc.get("accepted") or {}).values())
    rejected = sum(int(v) for v in (secoc.get("rejected") or {}).values())
    total = accepted + rejected
    return rejected / total if total else None


def _reasons(summary: dict[str, Any]) -> str:
    """One process's SecOC rejections by reason, e.g. ``bad_mac 100, unauthenticated 7``."""
    rejected = (summary.get("secoc") or {}).get("rejected") or {}
    return ", ".join(f"{k} {v}" for k, v in sorted(rejected.items()))


def loop_health(metrics: dict[str, Any], *, faults_injected: bool) -> dict[str, Any]:
    """The loop figures of a run's ``metrics`` (with its summaries and KPIs), the limits
    they are held against, and ``problems``: one sentence per limit passed.

    Keys: ``held`` (bool), ``problems`` (list of str), ``expected`` (faults injected: the
    problems do not degrade the run), ``secoc_reject_share`` ({process: share or None}),
    ``fallback_share``, ``deadline_miss_share`` (realtime), ``period_jitter_us_p99``
    (realtime, µs) and ``limits``."""
    plant = metrics.get("plant_summary") or {}
    ctrl = metrics.get("controller_summary") or {}
    realtime = metrics.get("mode") == "realtime"
    problems: list[str] = []
    shares = {"controller": _secoc_share(ctrl), "plant": _secoc_share(plant)}
    for name, summary in (("controller", ctrl), ("plant", plant)):
        share = shares[name]
        if share is not None and share > SECOC_REJECT_SHARE_MAX:
            problems.append(f"the {name} rejected {share:.0%} of the authenticated frames "
                            f"({_reasons(summary)}; limit {SECOC_REJECT_SHARE_MAX:.0%})")
    if bool((plant.get("secoc") or {}).get("enabled")) != bool((ctrl.get("secoc") or {})
                                                               .get("enabled")) \
            and plant and ctrl:
        problems.append("SecOC is on in one process only")
    cycles = int(plant.get("cycles") or 0)
    fallback = int(plant.get("fallback_cycles") or 0)
    fallback_share = fallback / cycles if cycles else None
    if fallback_passed(fallback, cycles):
        problems.append(fallback_text(fallback, cycles))
    miss_share = jitter = None
    if realtime:
        misses = metrics.get("deadline_misses")
        if misses is not None and cycles:
            miss_share = int(misses) / cycles
            if miss_share > DEADLINE_MISS_SHARE_MAX:
                problems.append(f"{misses} deadline misses in {cycles} cycles "
                                f"({miss_share:.1%}; limit {DEADLINE_MISS_SHARE_MAX:.0%})")
        jitter = metrics.get("period_jitter_us_p99")
        if jitter is not None and jitter > JITTER_P99_MAX_US:
            problems.append(f"period jitter p99 {jitter:.0f} µs (limit "
                            f"{JITTER_P99_MAX_US:.0f} µs)")
    return {"held": not problems, "problems": problems, "expected": faults_injected,
            "secoc_reject_share": shares, "fallback_share": fallback_share,
            "deadline_miss_share": miss_share, "period_jitter_us_p99": jitter,
            "limits": {"secoc_reject_share": SECOC_REJECT_SHARE_MAX,
                       "fallback_share": FALLBACK_SHARE_MAX,
                       "deadline_miss_share": DEADLINE_MISS_SHARE_MAX if realtime else None,
                       "period_jitter_us_p99": JITTER_P99_MAX_US if realtime else None}}


def apply_loop_verdict(metrics: dict[str, Any], *, faults_injected: bool) -> None:
    """Adds ``loop`` (:func:`loop_health`) to ``metrics``; a run that reached its end
    (``reason`` ``finished``) with a limit passed and no fault injected becomes ``degraded``
    and ``degraded_because`` lists the limits passed."""
    health = loop_health(metrics, faults_injected=faults_injected)
    metrics["loop"] = health
    if health["problems"] and not faults_injected and metrics.get("reason") == "finished":
        metrics["reason"] = DEGRADED
        metrics["degraded_because"] = list(health["problems"])


def loop_cell(metrics: dict[str, Any]) -> str:
    """The loop row of the KPI table: held, degraded, or the problems a fault explains."""
    health = metrics.get("loop")
    if not health:
        return "-"
    if health["held"]:
        return "held"
    return "faulted (expected)" if health["expected"] else "DEGRADED"
