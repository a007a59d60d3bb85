"""The report's Definitions section: what every number of report.md means, with this report's thresholds."""

from __future__ import annotations

from analysis.markdown import FAILURE_UNIT, plural
from analysis.stats import MIN_SEEDS_BOOTSTRAP, MIN_SEEDS_IQM
from analysis.tables import ReportOptions


def definitions(opts: ReportOptions, coverage: tuple[int, float] | None = None) -> list[str]:
    """The report's Definitions section, with this report's thresholds; ``coverage`` = (seeds, simulated
    coverage of the nominal bootstrap interval at that many seeds, stats.bootstrap_coverage)."""
    cover = (f" At {coverage[0]} seeds a nominal {opts.confidence:.0%} BCa interval of the IQM covers "
             f"{coverage[1]:.0%} of samples (simulated on normal data, 1000 draws): read it as that."
             if coverage else "")
    return ["## Definitions", "",
            "- Evaluation (every `eval.every_iters`, sampler-independent, deterministic policy): episodes start at "
            "stratified frames of every bin (the same number in each) and run for the horizon or to the end of "
            "their clip; an episode fails when it terminates, when its world breaks (non-finite or out of "
            "bounds; counted as `broken` where recorded) or, with `eval.max_mpkpe_rel_mm`, when it tracks worse.",
            f"- **Overall failure** of an evaluation = failed episodes / started episodes ({FAILURE_UNIT}); success "
            "= 1 − failure. It is not the mean of the per-bin rates: an episode spans several bins.",
            f"- **Clip and segment failure** are in the same unit ({FAILURE_UNIT}), each episode charged to the "
            "clip (segment) it started in, so the overall failure is their mean weighted by started episodes.",
            "- **Per-bin failure rate** (bin heatmaps, failure per bin, mastery) is a different unit, per *visit*: "
            "the failures that happened at the bin's frames over the episodes that were at one of its frames; the "
            "figures say \"per visit\".",
            f"- A bin counts as mastered at an evaluation where its per-visit failure rate is < "
            f"{opts.mastery_threshold:g} (a horizon-truncated bin also needs an episode that tracked all its frames "
            "after entering from an earlier bin). Its mastery iteration in one seed = the first evaluation from which "
            f"it counts as mastered for {plural(opts.mastery_persist, 'consecutive evaluation')} or for the rest of "
            "the run; a seed that never got there is censored at its last evaluation.",
            f"- Time to threshold = the first evaluation from which overall success ≥ the threshold "
            f"({opts.success_threshold:g} in the Arms table) with the same persistence, per seed, in iterations, env "
            "steps and wall time (censored likewise).",
            "- Per arm, such times are summarised by the Kaplan-Meier (KM) median over seeds: only when more than "
            "half of the seeds got there (censored seeds count as not yet), else `not reached`.",
            "- Speedup = baseline median / arm median (> 1: the arm is faster), at every success threshold from "
            "0.5 to 0.99 (the speedup curve). `estimate` when both medians are defined (bootstrap interval over "
            f"seeds, each arm resampled on its own, when every arm has ≥ {MIN_SEEDS_BOOTSTRAP} seeds); `lower_bound` "
            "when only the baseline's median was not reached (its last follow-up over the arm's median); "
            "`upper_bound` the reverse; `not_estimable` when neither was. One speedup is never quoted without "
            "its threshold.",
            "- Iso-failure ratio: at each evaluation of the baseline, its time over the time at which the arm's "
            "curve (IQM over seeds) first got to the baseline's failure there, interpolated linearly between "
            "evaluations.",
            "- Sampling probability mass of a clip: the training sampler's probability summed over the clip's "
            "bins (sampler.parquet), the mean over the logged iterations, then over seeds. Effective support = "
            "(1 / Σ p²) / S over the S bins (1: uniform); largest p relative to uniform = max p × S; over clips "
            "the same with the clips' masses and their number C. A sampler's signal is flat when it is equal in "
            "every bin; a signal flat at every logged iteration of every seed is degenerate.",
            "- Smoothness of the policy itself (where recorded): action rate = Σ over joints of (a_t − a_{t−1})² "
            "per step (the MDP's action_rate_l2 term); joint acceleration = mean over joints of |Δ joint "
            "velocity| / control period (rad/s²); both step-weighted means over the evaluation like the tracking "
            "errors. Joint-velocity *error* is a tracking error, not a smoothness measure.",
            f"- Point estimates: IQM (mean of the middle half of the seeds) from {MIN_SEEDS_IQM} seeds, else the "
            f"mean. Intervals: BCa bootstrap (percentile where BCa is undefined) only when every arm has "
            f"≥ {MIN_SEEDS_BOOTSTRAP} seeds; with fewer, the range of the seeds, labelled so.{cover} Per-seed "
            "values are listed beside every estimate.",
            "- Differences: two-sided permutation test over seeds (exact for small n) of the difference of per-seed "
            "means, and the difference printed beside it is that difference of means; claimed at p < "
            f"{opts.alpha:g}. With n and m seeds no exact test gives p below 2 / C(n + m, n) (the smallest "
            "attainable p, printed beside every p). Tests against the lowest arm are post hoc and uncorrected; "
            "tests against the baseline also get Holm's adjustment for their number. Times to an event are "
            "compared with Gehan's generalised Wilcoxon scores (censoring-aware). Exact ties name no winner.",
            "- Wall time is compared only between runs of one machine kind (provenance.json).", ""]
