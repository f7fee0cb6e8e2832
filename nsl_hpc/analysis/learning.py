"""Did the models learn? Per (system, arch) of a merged sweep, the share of tasks that score no better than the mean
predictor (the constant output at the training data's mean, each row's ``mean_predictor_nmae``; a task learned where
its nmae is below ``nsl.learning.below`` times that), or did not finish with finite scores; the worst of them by
name; and a flag where more than ``nsl.learning.flag_share`` of its better-resourced tasks, those above the
``nsl.learning.above_quantile`` quantile of the pair's ``nsl.learning.resource``, did not learn: such a pair's laws
describe models that fail, not the scaling of ones that identify the system. (The grid's smallest budgets, 2 epochs
or n_i = n_l iterations on the least data, leave many tasks of every architecture untrained by design: they are
counted, not flagged.)
"""

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from nsl_hpc.analysis.fitting import pair_outcomes
from nsl_hpc.analysis.nsl_settings import Learning, Nsl

MEAN_PREDICTOR = "mean_predictor_nmae"  # the rows' column of the mean predictor's nmae


@dataclass(frozen=True)
class PairLearning:
    """How the tasks of one (system, arch) learned."""

    system: str
    arch: str
    tasks: int
    not_learned: int  # tasks at or above the mean predictor's nmae, or without finite scores
    above: int  # tasks above the quantile of the resource ...
    not_learned_above: int  # ... and those of them that did not learn
    worst: str  # the task that scored worst, with its score and the mean predictor's
    flagged: bool
    why: str = ""  # a flagged pair: why its better-resourced tasks failed, and what to change (``diagnosis``)

    @property
    def share(self) -> float:
        return self.not_learned / self.tasks

    @property
    def share_above(self) -> float:
        return self.not_learned_above / self.above if self.above else 0.0

    def lines(self) -> list[str]:
        """A command's output: one line, and for a flagged pair a second that says why and what to change."""
        flag = "  NOT LEARNING" if self.flagged else ""
        line = (f"{self.system} / {self.arch}: {self.not_learned:,} of {self.tasks:,} tasks ({self.share:.0%}) no "
                f"better than the mean predictor, {self.not_learned_above:,} of the {self.above:,} better-resourced "
                f"({self.share_above:.0%}); worst {self.worst}{flag}")
        return [line, f"    why: {self.why}"] if self.flagged else [line]


def learned(results: pa.Table, below: float) -> np.ndarray:
    """Mask of the rows whose model learned: status ok and an nmae below ``below`` times the mean predictor's (all
    False where the rows carry no mean predictor's score)."""
    if MEAN_PREDICTOR not in results.column_names:
        return np.zeros(results.num_rows, dtype=bool)
    nmae = results["nmae"].to_numpy(zero_copy_only=False).astype(float)
    mean = results[MEAN_PREDICTOR].to_numpy(zero_copy_only=False).astype(float)
    ok = np.asarray(results["status"].to_pylist()) == "ok"
    with np.errstate(invalid="ignore"):
        return ok & np.isfinite(nmae) & (nmae < below * mean)


def pair_learning(results: pa.Table, system: str, arch: str, settings: Learning, column: str) -> PairLearning:
    """``PairLearning`` of the (system, arch) rows of ``results``; ``settings``: the ``nsl.learning`` group,
    ``column``: the results column of its resource."""
    rows = pair_outcomes(results, system, arch)
    failed = ~learned(rows, settings.below)
    resource = rows[column].to_numpy(zero_copy_only=False).astype(float)
    above = resource > np.quantile(resource, settings.above_quantile) if settings.above_quantile else \
        np.ones(rows.num_rows, dtype=bool)
    nmae = rows["nmae"].to_numpy(zero_copy_only=False).astype(float)
    worst = int(np.argmax(np.where(np.isfinite(nmae), nmae, np.inf)))
    mean = rows[MEAN_PREDICTOR][worst].as_py() if MEAN_PREDICTOR in rows.column_names else None
    worst_text = (f"{rows['task_id'][worst].as_py()} (nmae {nmae[worst]:.3g}, status {rows['status'][worst].as_py()}"
                  + (f", mean predictor {mean:.3g})" if mean is not None else ")"))
    not_above = int((failed & above).sum())
    flagged = bool(above.sum()) and not_above > settings.flag_share * above.sum()
    return PairLearning(system, arch, rows.num_rows, int(failed.sum()), int(above.sum()), not_above, worst_text,
                        flagged, diagnosis(rows, failed & above, ~failed & above, nmae) if flagged else "")


def diagnosis(rows: pa.Table, failed: np.ndarray, learned_too: np.ndarray, nmae: np.ndarray) -> str:
    """Why the ``failed`` tasks of a flagged pair failed, against the ``learned_too`` ones beside them (masks over
    ``rows``): scores that are not finite (diverged), fewer optimizer steps (the rows' ``steps``) than the tasks that
    learned, or as many (the model, not its training)."""
    diverged = int((failed & ~np.isfinite(nmae)).sum())
    if diverged * 2 > failed.sum():
        return (f"{diverged} of the {int(failed.sum())} diverged or did not finish with finite scores: lower "
                "train.lr or train.grad_clip_norm, or check the scaling of the data")
    steps = rows["steps"].to_numpy(zero_copy_only=False).astype(float) if "steps" in rows.column_names else None
    if steps is None or not learned_too.any():
        return ("none of its better-resourced tasks learned: check the architecture's layout and the system's data "
                "(docs/fits.md, Did the models learn)")
    few, many = float(np.median(steps[failed])), float(np.median(steps[learned_too]))
    if few * 2 <= many:
        return (f"the better-resourced tasks that failed trained a median of {few:,.0f} optimizer steps, those that "
                f"learned {many:,.0f}: train longer (more epochs, or a larger iteration multiplier, in the grid)")
    return (f"the better-resourced tasks that failed trained as long as those that learned (a median of {few:,.0f} "
            f"optimizer steps against {many:,.0f}): the model, not its training length, fails here; check the "
            "architecture's layout (docs/fits.md, Did the models learn)")


def sweep_learning(results: pa.Table, nsl: Nsl) -> list[PairLearning]:
    """``pair_learning`` of every (system, arch) of ``results`` by the ``nsl`` group's ``learning`` settings, in the
    order they first appear; none where the rows carry no mean predictor's score (a sweep from before it was
    recorded)."""
    if MEAN_PREDICTOR not in results.column_names:
        return []
    settings = nsl.learning
    column = nsl.resources[settings.resource].column
    pairs = dict.fromkeys(zip(results["system"].to_pylist(), results["arch"].to_pylist(), strict=True))
    return [pair_learning(results, system, arch, settings, column) for system, arch in pairs]


def learning_lines(pairs: Sequence[PairLearning]) -> list[str]:
    """The command output: one line per pair, flagged pairs marked."""
    if not pairs:
        return ["learning: the rows carry no mean predictor's score (mean_predictor_nmae): a sweep from before it"]
    return [line for pair in pairs for line in pair.lines()]
