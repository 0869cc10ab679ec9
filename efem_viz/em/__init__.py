"""EFEM solver: proposal pool, config presets, elimination rules, trace recording and replay, results.

Light at import time (no torch): the solver imports torch inside its functions.
"""

from __future__ import annotations

from efem_viz.em.config import PRESETS, EMConfig, preset
from efem_viz.em.estep import schedule
from efem_viz.em.replay import TraceReplay
from efem_viz.em.results import EMResult, Instances, ResultFileError
from efem_viz.em.rules import REVIEW_RULES, STEP_RULES, Kill, ReviewRecord, ReviewRule, StepContext, StepRule
from efem_viz.em.solver import EMCancelled, StepInfo, run_em
from efem_viz.em.trace import DeathEvent, EMTrace, ProposalView

__all__ = [
    "PRESETS",
    "REVIEW_RULES",
    "STEP_RULES",
    "Kill",
    "ReviewRecord",
    "ReviewRule",
    "StepContext",
    "StepRule",
    "TraceReplay",
    "DeathEvent",
    "EMCancelled",
    "EMConfig",
    "EMResult",
    "EMTrace",
    "Instances",
    "ProposalView",
    "ResultFileError",
    "StepInfo",
    "preset",
    "run_em",
    "schedule",
]
