"""The ground-truth-free acceptance test: its statistic, and the record of what it decided.

For a correction and a sequence, every frame pair i gives a *paired* difference
``Δ_i = L_i(ξ) − L_i(0)``: the gradient-masked photometric error of the temporal reconstructions
(``dpc_jax.nn.losses.temporal_pair_errors``) with the correction and without it, with the same depth
and validity. Δ < 0 means the corrected relative pose reconstructs the pair better. A part of a
correction passes when its Δ are significantly below zero by the one-sided Wilcoxon signed-rank test
(``scipy.stats.wilcoxon``, ``alternative="less"``) at level ``alpha`` *and* their mean is negative
(:func:`paired_test`). The same test compares two corrections on the same pairs: the differences
``Δ_i(a) − Δ_i(b) = L_i(a) − L_i(b)`` below zero say that ``a`` explains the pairs better than ``b``
(the correction's mean against its remainder, the adapted network against the trained one).
Consecutive pairs share images and motion, so the Δ are not independent and the p-value is
optimistic; the default level 0.01 is chosen strict for that reason.

What to apply, from the tests of the correction's parts, is ``dpc_jax.correction.decision``'s;
``dpc_jax.results.acceptance.Acceptance`` records it.

**While the pairs arrive** (the live correction, ``dpc_jax.correction.live``) the same paired differences
are tested sequentially: a test that is checked after every pair must keep its false-acceptance rate
under that continuous monitoring, which a fixed-sample p-value does not. :class:`SequentialTest` is a
test by betting: the wealth ``W_t = Π_k (1 + λ s_k)``, ``s_k`` the sign of the k-th difference (+1 when
the correction helped the pair, −1 when it hurt, 0 when it did neither), averaged over a grid of bets
λ, is a nonnegative supermartingale while the correction helps on at most half the pairs, so by Ville's
inequality ``P(sup_t W_t ≥ 1/α) ≤ α``: accepting at the first ``t`` with ``W_t ≥ 1/α`` (and the mean
difference so far below zero, as offline) falsely accepts with probability at most α however long it
runs. An accepted part is withdrawn when the evidence turns: a CUSUM of the signs (Page's test of the
rate the correction helped at, while accepted, against one half) raises an alarm within a few pairs of
a change of scene, lighting or camera that makes the correction neutral or harmful; the test then
starts again with a smaller level (α spending: the j-th acceptance is at ``α · 6 / (π² j²)``, which
sums to α over all of them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dpc_jax.results.acceptance import PairedTest

DEFAULT_ALPHA = 0.01


def paired_test(name: str, delta: np.ndarray, alpha: float = DEFAULT_ALPHA) -> PairedTest:
    """One-sided Wilcoxon signed-rank test of ``delta`` (``[M]``) < 0 (see the module docstring)."""
    from scipy import stats

    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    delta = np.asarray(delta, np.float64)
    if delta.ndim != 1 or delta.size == 0 or not np.all(np.isfinite(delta)):
        raise ValueError(f"{name}: Δ must be a non-empty vector of finite numbers, got {delta.shape}")
    mean = float(delta.mean())
    if np.count_nonzero(delta) == 0:
        statistic, p_value = math.nan, 1.0
    else:
        result = stats.wilcoxon(delta, alternative="less", zero_method="wilcox")
        statistic, p_value = float(result.statistic), float(result.pvalue)
    return PairedTest(
        component=name,
        pairs=int(delta.size),
        mean_delta=mean,
        median_delta=float(np.median(delta)),
        improved_share=float(np.mean(delta < 0)),
        statistic=statistic,
        p_value=p_value,
        passed=bool(p_value < alpha and mean < 0),
        std_delta=float(delta.std()),
    )


# The bets averaged by the sequential test: a mixture of bets is itself a test martingale, and it grows
# nearly as fast as the best single bet for the rate the correction actually helps at.
BETS = np.linspace(0.05, 0.8, 16)
# The CUSUM's alarm level (log of the likelihood ratio): a withdrawal needs about this much evidence that
# the correction helps on no more than half the pairs.
WITHDRAW_LOG_LR = math.log(100.0)


@dataclass
class SequentialTest:
    """The live test of one paired difference (module docstring): fed one difference per pair
    (:meth:`update`), ``accepted`` says whether the part may be applied to the pair after it.

    ``alpha``: the level over all acceptances (α spending); ``name``: what is tested. The state is a
    handful of numbers, whatever the number of pairs.
    """

    name: str
    alpha: float = DEFAULT_ALPHA
    accepted: bool = False
    pairs: int = 0  # pairs seen
    episode_pairs: int = 0  # pairs since the test (re)started or was accepted
    acceptances: int = 0  # how many times it was accepted
    withdrawals: int = 0
    log_wealth: np.ndarray = field(default_factory=lambda: np.zeros(BETS.size))
    episode_sum: float = 0.0  # sum of the differences since the test (re)started
    total: float = 0.0  # sum of all the differences
    helped: int = 0  # pairs with a negative difference since acceptance
    signed: int = 0  # pairs with a nonzero difference since acceptance
    cusum: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 < self.alpha < 1.0:
            raise ValueError(f"alpha must be in (0, 1), got {self.alpha}")

    @property
    def level(self) -> float:
        """The level of the next acceptance: α · 6 / (π² j²) for the j-th."""
        j = self.acceptances + 1
        return self.alpha * 6.0 / (math.pi**2 * j**2)

    @property
    def mean(self) -> float:
        """The mean of all the differences seen (nan before the first)."""
        return self.total / self.pairs if self.pairs else math.nan

    @property
    def evidence(self) -> float:
        """The mixture wealth ``W_t`` (accepting at ``1 / level``), or the CUSUM while accepted."""
        return self.cusum if self.accepted else float(np.mean(np.exp(self.log_wealth)))

    def update(self, delta: float) -> str | None:
        """Take the difference of the next pair; ``"accepted"`` or ``"withdrawn"`` when the state changes
        at this pair, else None."""
        if not math.isfinite(delta):
            raise ValueError(f"{self.name}: the difference of pair {self.pairs} is not finite")
        self.pairs += 1
        self.episode_pairs += 1
        self.total += delta
        sign = -float(np.sign(delta))  # +1: the correction helped this pair
        if not self.accepted:
            self.log_wealth += np.log1p(BETS * sign)
            self.episode_sum += delta
            if self.episode_sum < 0 and float(np.mean(np.exp(self.log_wealth))) >= 1.0 / self.level:
                self.accepted, self.acceptances = True, self.acceptances + 1
                self.episode_pairs = self.helped = self.signed = 0
                self.cusum = 0.0
                return "accepted"
            return None
        self.helped += sign > 0
        self.signed += sign != 0
        # The rate it helps at while accepted (a prior of two helped pairs in three keeps the ratio finite):
        # the alarm tests a fall from that rate to one half.
        rate = min(0.95, max(0.6, (self.helped + 2) / (self.signed + 3)))
        if sign:
            self.cusum = max(0.0, self.cusum + math.log(0.5 / (rate if sign > 0 else 1.0 - rate)))
        if self.cusum >= WITHDRAW_LOG_LR:
            self.accepted, self.withdrawals = False, self.withdrawals + 1
            self.log_wealth = np.zeros(BETS.size)
            self.episode_sum = 0.0
            self.episode_pairs = 0
            return "withdrawn"
        return None

