"""Benchmark seeds: the one declared tuning seed and the evaluation seeds (evaluation rules of the project).

Every knob chosen by looking at results (simulated perception knobs, temperatures, planner constants, stopping
thresholds) is chosen on :data:`TUNING_SEED` only; published figures come from :data:`EVALUATION_SEEDS`, never
used for tuning. Seed 0 is the legacy seed on which the first figures were both tuned and published, so it is
neither. Tools that tune call :func:`check_tuning_seed`; evaluations may run any seed but label those outside
:data:`EVALUATION_SEEDS`.
"""

from __future__ import annotations

TUNING_SEED = 11
EVALUATION_SEEDS: tuple[int, ...] = (1, 2, 3)
LEGACY_SEED = 0


def check_tuning_seed(seed: int) -> int:
    """Return ``seed`` if a tuning tool may look at results on it, else raise ``ValueError`` saying what to use."""
    if seed in EVALUATION_SEEDS:
        raise ValueError(
            f"seed {seed} is an evaluation seed ({', '.join(map(str, EVALUATION_SEEDS))}); tune on the tuning "
            f"seed {TUNING_SEED} (eqa.seeds.TUNING_SEED) and evaluate on the others"
        )
    if seed == LEGACY_SEED:
        raise ValueError(f"seed 0 carries the legacy published figures; tune on seed {TUNING_SEED} instead")
    return seed


def seed_role(seed: int) -> str:
    """``"tuning"``, ``"evaluation"``, ``"legacy"`` or ``"other"``: how figures from ``seed`` must be labelled."""
    if seed == TUNING_SEED:
        return "tuning"
    if seed in EVALUATION_SEEDS:
        return "evaluation"
    if seed == LEGACY_SEED:
        return "legacy"
    return "other"
