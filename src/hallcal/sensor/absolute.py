"""Absolute angle at power-up: which pole pair the rotor is in, from the magnets' own signatures.

f_init (eq. fimp) only knows the electrical angle: after a power-up it starts within one
electrical period of zero, a whole number ``j`` of pole pairs ``2 pi j / n_m`` away from the
calibration's frame, and the table of eq. (f_final) is then applied to the wrong magnets. The
identified flux model g_theta knows each magnet's individual shape (the harmonics that are not
multiples of n_m, section "Model structure"), so the offset ``j`` is a parameter of the
measurement model ``d_k = g_theta(y0_k) + v_k`` (eq. d_h, white Gaussian noise) and can be
estimated by maximum likelihood among the n_m hypotheses, sample by sample, with a sequential
probability ratio test deciding when it is certain (Wald 1945; for n_m hypotheses the posterior
form of the multi-hypothesis SPRT, Baum & Veeravalli 1994, IEEE Trans. Inf. Theory 40(6)).

Geometry. Write the f_init output after power-up as ``y_k = (psi_k + 2 pi m_k) / n_m`` with the
wrapped electrical angle ``psi_k = atan2(beta_k, alpha_k)`` and f_init's integer turn count
``m_k``. Hypothesis j says the calibration frame's f_init value is ``y_k + 2 pi j / n_m``. Every
hypothesis predicts the *same* electrical angle psi_k (that is all f_init tracks), so tracking
with f_init's increments alone never separates them; what separates them is the part of
``d - o`` that f_init throws away: the radius ``rho = |P (d - o)|`` in the alpha/beta plane and
the component ``zeta = n . (d - o)`` along the null vector ``n`` of the projection P
(zero-sequence for Clarke). Both are tabulated over the revolution in the calibration frame.

Per-sample evidence (first-order profile likelihood). With the predicted point
``c_j(psi) = o + R_j(psi) u(psi) + Z_j(psi) n`` (``u = P^+ [cos psi, sin psi]``) and its
tangent ``c_j' = R_j' u + R_j v + Z_j' n`` (``v = P^+ [-sin psi, cos psi]``), the residual at
the measured angle is ``r = (rho - R_j) u + (zeta - Z_j) n`` and the sample's cost is

    e_j = r' S r - (t' S r)^2 / (t' S t),       S = Sigma^{-1},  t = c_j'

i.e. the squared Mahalanobis distance to the hypothesis's curve after minimizing over the angle
along it (one Gauss-Newton step; exact to first order in the noise). Under the true hypothesis
e_j is chi-square with 2 degrees of freedom; ``Lambda_j = sum_k e_j,k = -2 log L_j + const``.
Moving data simply contribute samples at other angles: the hypotheses stay tied to f_init's
turn count, so motion adds evidence wherever the magnets differ.

Decoder specification (for firmware; :class:`PowerUpIdentifier` is the reference)
---------------------------------------------------------------------------------
Constants (:class:`PowerUpDecoder`, all float64 in the reference):

- ``n`` pole pairs, ``L`` grid points per electrical period, ``M = n L``;
- ``P`` (2 x 3) and ``o`` (3): f_init's projection and offsets (as the lookup table's);
- ``nv`` (3): unit null vector of P, ``cross(P[0], P[1]) / |cross(P[0], P[1])|``;
- ``A`` (2 x 2, symmetric), ``B`` (2), ``C``: ``A = P+' S P+``, ``B = P+' S nv``,
  ``C = nv' S nv`` with ``P+ = pinv(P)`` and the noise precision ``S = Sigma^{-1}``
  (``Sigma = sigma^2 I`` from calibration, so costs are in noise-sigma units squared);
- tables ``R[q]``, ``Z[q]``, ``q = 0..M-1``: rho and zeta of the model flux at the calibration
  frame's f_init angle ``y_q = 2 pi q / M`` (i.e. at the true angle y0 solving
  ``f_init(g_theta(y0)) = y_q`` exactly), so ``atan2`` of the table point is ``2 pi q / L``;
- ``alpha``: accepted error probability; lock when the best posterior >= 1 - alpha;
- ``cap``: censoring level of one sample's cost, ``2 ln 100`` (a clean sample exceeds it once
  in a hundred): Huber's censored probability-ratio test (Huber 1965, Ann. Math. Statist.
  36(6)), the likelihood of Gaussian noise contaminated by rare outliers; one sample then weighs
  at most a likelihood ratio of 100 against any hypothesis, so with alpha < 1 % no single sample
  (a glitch) can lock.
- ``w``: the common-gain prior's information ``1 / gain_sd^2`` (only with the gain profile,
  ``gain_sd > 0``; see "Common gain" below); ``T``: electrical turns of motion before the lock
  (0: none; see "Sensors changed since calibration");
- ``wt``, ``kd``, ``bd``, ``bf``: the misfit test's weight ``(1 - 1 / kappa) / 2``, drift
  ``ln kappa`` and bounds ``ln(1 / beta)``, ``ln(1 / gamma)`` (:mod:`hallcal.sensor.misfit`:
  does any pole pair fit at all?);
- ``K0``, ``gz``, ``g4``: the goodness-of-fit gate at the lock (see "Sensors changed since
  calibration"): the samples of evidence before the lock ``K0`` (:data:`DEFAULT_GATE_SAMPLES`),
  and ``gz = 2 (z^2 - 1) / 3``, ``g4 = 4 z^2`` with ``z`` the standard normal quantile of
  ``1 - alpha_g`` (``alpha_g`` the gate's false-alarm rate, :data:`DEFAULT_GATE_RATE`); without
  the gate ``K0 = 0`` and step 7's gate always passes (artifacts made before it);
- ``cb``: the bound of the gate's bias half, ``phi_b 2 ln(2 / alpha_g)`` (the winner's
  residual mean, :mod:`hallcal.sensor._absolute_gate`; the chi-square half's ``z`` is then the
  quantile of ``1 - alpha_g / 2``); without it (artifacts made before it, or no
  ``gate_bias_dispersion``) ``cb = inf`` and the bias half always passes.

State: ``m`` (integer turn count, 0), ``psi_prev`` (none yet), ``Lam[j] = 0`` for j = 0..n-1,
``locked = false``, ``mismatch = false``, ``best = 0``, ``D = 0`` (misfit statistic), ``Q = 0``
(the best hypothesis's whole cost), ``k = 0`` (samples of evidence); with the gain profile
also ``s[j] = 1`` and ``I[j] = w``; with the bias half ``h[j] = (0, 0, 0, 0, 0)``.

Per sample ``d = (d1, d2, d3)``:

1. ``x = d - o``; ``al = P[0].x``; ``be = P[1].x``; ``rho = sqrt(al^2 + be^2)``;
   ``psi = atan2(be, al)`` in (-pi, pi]; ``zeta = nv.x``.
2. Turn count (f_init's unwrap from y = 0 before the first sample, eq. fimp):
   first sample ``m = -floor((psi + pi) / (2 pi))``, later ``m -= floor((psi - psi_prev + pi) /
   (2 pi))``; ``psi_prev = psi``. f_init's output is ``y = (psi + 2 pi m) / n``.
3. If locked, or mismatch, or ``rho <= 1e-12 * (1 + |R[0]|)`` (no angle information), stop
   here. Else ``k += 1``.
4. ``c = al / rho``, ``s = be / rho``;
   ``Guu = A00 c^2 + 2 A01 c s + A11 s^2``, ``Gvv = A00 s^2 - 2 A01 c s + A11 c^2``,
   ``Guv = (A11 - A00) c s + A01 (c^2 - s^2)``, ``Gun = B0 c + B1 s``, ``Gvn = B1 c - B0 s``,
   ``Gnn = C``.
5. For each hypothesis j = 0..n-1:

   - table coordinate ``x_j = ((m + j) mod n) L + L psi / (2 pi)`` (mod taken into 0..n-1);
     if ``x_j < 0``: ``x_j += M``; ``i = floor(x_j)``, if ``i >= M``: ``i = M - 1``;
     ``f = x_j - i``; ``i1 = i + 1`` or 0 when ``i = M - 1``;
   - ``Rj = R[i] + f (R[i1] - R[i])``, ``Zj = Z[i] + f (Z[i1] - Z[i])``,
     ``dR = (R[i1] - R[i]) L / (2 pi)``, ``dZ = (Z[i1] - Z[i]) L / (2 pi)`` (per electrical rad);
   - ``a = rho - Rj``, ``b = zeta - Zj``;
   - ``rr = a^2 Guu + 2 a b Gun + b^2 Gnn``;
     ``tr = a (dR Guu + Rj Guv + dZ Gun) + b (dR Gun + Rj Gvn + dZ Gnn)``;
     ``tt = dR^2 Guu + Rj^2 Gvv + dZ^2 Gnn + 2 dR Rj Guv + 2 dR dZ Gun + 2 Rj dZ Gvn``;
   - without the gain profile: ``Lam[j] += min(rr - tr^2 / tt, cap)``;
   - with it (``a = rho - s[j] Rj``, ``b = zeta - s[j] Zj`` above instead):
     ``e = rr - tr^2 / tt``, ``tp = Rj (dR Guu + Rj Guv + dZ Gun) + Zj (dR Gun + Rj Gvn + dZ Gnn)``,
     ``pr = Rj (a Guu + b Gun) + Zj (a Gun + b Gnn) - tp tr / tt``,
     ``pp = Rj^2 Guu + 2 Rj Zj Gun + Zj^2 Gnn - tp^2 / tt``, ``inc = e - pr^2 / (I[j] + pp)``;
     ``u = 1`` if ``inc <= cap`` else ``cap / inc``; ``I[j] += u pp``;
     ``s[j] += u pr / I[j]``; ``Lam[j] += min(inc, cap)``;
   - with the bias half (no gain profile), ``e = rr - tr^2 / tt`` the uncensored cost,
     ``u = cap / max(e, cap)``, ``tu = dR Guu + Rj Guv + dZ Gun``,
     ``tn = dR Gun + Rj Gvn + dZ Gnn``: ``h[j] += u (a Guu + b Gun - tu tr / tt,
     a Gun + b Gnn - tn tr / tt, Guu - tu^2 / tt, Gun - tu tn / tt, Gnn - tn^2 / tt)``.
6. ``Lmin = min_j Lam[j]``, ``best`` = the smallest j attaining it; ``Lam[j] -= Lmin`` for all j
   (keeps the numbers bounded; the posterior only depends on differences). The sum of the Lmin
   so far is the best hypothesis's whole cost: ``Q += Lmin``; ``D += wt Lmin - kd`` (the misfit
   statistic);
   if ``D >= bd``: ``mismatch = true`` (no pole pair fits: the signals do not match this
   calibration), stop here for good.
7. ``W = sum_{j != best} exp(-Lam[j] / 2)``; posterior of best ``p = 1 / (1 + W)``; lock when
   ``W <= alpha / (1 - alpha)`` (i.e. p >= 1 - alpha) and ``D <= -bf`` (the best fits) and,
   with a travel ``T > 0`` (``lock_travel``), f_init's electrical angle ``psi + 2 pi m`` has
   spanned at least ``2 pi T`` (max - min over the samples of evidence so far), and ``k >= K0``
   samples of evidence. The first time all of these hold, the gate: with ``x = Q - 2 k - gz``,
   the best fits when ``x <= 0`` or ``x^2 <= g4 k`` (Q within the chi-square(2 k) quantile of
   ``1 - alpha_g``); then lock, else ``mismatch = true`` (the data fit no pole pair as the
   calibration's noise allows), stop here for good. With the bias half, also (the same
   first time, same outcome): with ``(ha, hb, Haa, Hab, Hbb) = h[best]``, the best fits only
   when ``Hbb ha^2 - 2 Hab ha hb + Haa hb^2 <= cb (Haa Hbb - Hab^2)`` (its residual's mean
   within the chi-square(2) quantile). Margin ``sqrt(min_{j != best} Lam[j])`` in
   noise sigmas (the log-likelihood-ratio margin is half its square).

Output: the calibration frame's f_init value ``y_abs = y + 2 pi best / n``, and the corrected
angle ``y_star = y_abs + eta(y_abs)`` with the lookup table of eq. (f_final). Before the lock
``best`` is the current maximum-likelihood choice (it may still change); f_init's electrical
angle is right from the first sample either way, so commutation never waits for the decision.
The first output lies in [-pi/n, 2 pi - pi/n) (the calibration frame modulo one revolution);
later outputs are continuous.

Common gain. All sensors' signals scaled by s about f_init's offsets (the magnets'
temperature: NdFeB remanence -0.12 %/K) leave psi unchanged and scale rho, zeta and the
tangent; hypothesis j's cost over the samples so far is then ``sum_k e_jk(s) + w (s - 1)^2``,
quadratic in s, and its minimum over s is kept by a recursive least-squares update: ``s[j]`` the
estimate, ``I[j]`` its information (``w`` plus the ``pp`` of the samples), ``inc`` exactly what
the profiled cost grows by with the new sample (Laplace-equivalent to integrating s out: the
Occam factors of the hypotheses differ by their radii, about 1 %). Censoring stays per sample
(no sample brings more than cap); a censored sample still moves s, with Huber's bounded
weight ``cap / inc`` (Huber 1964, Ann. Math. Statist. 35(1)), so that one hypothesis whose
first samples were censored is not held at a wrong s for good. The price: at standstill a
common gain and a magnet's strength look alike, so only the direction of (rho, zeta) across the
curve separates the pole pairs, which one sensor's own gain or offset moves; hence the
calibration keeps the profile only where it makes the lock more robust
(:func:`analyze_calibration`). ``gain_sd = 0`` is the decoder without it (s = 1; artifacts
made before it).

Sensors changed since calibration. The decoder assumes the calibrated sensors (up to the common
gain, with the profile): a change moves the measured point off the right hypothesis's curve,
and where the magnets differ by little it can move it onto a wrong one, which then wins the
lock and passes the misfit test. :mod:`hallcal.sensor.drift_margin` measures from the tables how
large a change that takes (:attr:`IdentifiabilityReport.drift`). Where a plausible one suffices
(one sensor's gain or offset by 1 %, all by 5 %), no decoder can be certain at standstill: a
common gain looks like a magnet's strength, and once it is profiled one sensor's drift moves
the remaining evidence onto another magnet. Over one electrical revolution of motion one
sensor's change is the same pattern in the electrical angle under every hypothesis while the
magnets differ, so :func:`analyze_calibration` gives such a calibration the profile and the
travel ``T = 1`` (:data:`DEFAULT_LOCK_TRAVEL`).

Where the plain lock survives the plausible drifts, a larger change (one sensor's gain by 5-10 %,
an offset by 5 %, a 3 % common gain: tens of noise sigmas) mostly puts the point far from every
curve (the misfit test refuses), but in a few per cent of positions next to a wrong pole pair's
curve, within a noise sigma or two. Measured before the gate (``benchmarks/
bench_powerup_margin.txt``, 5 motors, 11 changes, 40 power-ups each): 73 wrong locks in 2200;
two kinds. Locks after 15-110 samples whose best cost was already 1.7-2.3 times the noise's
per degree of freedom (chi-square p-value 1e-3 to 1e-25): the misfit test accepts any cost
below 2.4 times the noise's (kappa = 8), and its statistic drifts down slowly there. And quick
locks (5-12 samples) on a wrong curve within about one sigma: at standstill nothing in 6
samples tells that from noise (a bias b per sample adds k b^2 to a chi-square(2 k) cost). Hence the
gate (step 7): the winner's whole cost against the chi-square(2 k) quantile of ``1 - alpha_g``
(Cornish-Fisher to the constant term: the tail probability at the bound is alpha_g = 1e-4 within 2 %
at k = 96, 15 % at k = 6), once, at the first sample the lock rule holds, and not before ``K0``
samples of evidence: at K0 = 96 it sees a constant misfit of one noise sigma per sample (cost 1.5
times the noise's, :data:`~hallcal.sensor.misfit.CONFIRM_RATIO`) with probability 0.69, half a
sigma^2 with 0.09. Under the calibrated noise the gate refuses a healthy power-up with probability
alpha_g (the cost of the best is at most the right hypothesis's, a chi-square(2 k) sum); the price
is the healthy lock after K0 samples instead of about 6. A rig whose noise is not white (the ring
jig's bursts) gets the quantile widened by the dispersion phi its calibration recording shows
(:func:`gate_dispersion`): its false alarm stays near alpha_g, its power is what that noise
leaves. Only the standstill lock has the gate: the lock after motion (``T > 0``) already keeps
out these wrong locks, and over its thousands of samples the gate would refuse plausible drifts.

The gate's bias half. After the gate the wrong locks left (16 of 2200) all came at K0 with a
whole cost 1.05-1.42 times the noise's: a changed sensor puts the point at a fixed offset from
a wrong curve, a constant residual the total cost barely sees (``k |delta|^2`` against a
quantile margin of ``z sqrt(4 k)``, about 72 noise variances at k = 96). The likelihood-ratio
test of a constant residual mean (chi-square(2) under the calibrated noise, whatever k;
:mod:`hallcal.sensor._absolute_gate`) sees it from about 20: wrong locks 16 -> 3 of 2200, the
healthy power-ups locking as before, at K0. The two halves take ``alpha_g / 2`` each
(Bonferroni), so the gate's false alarm stays at most alpha_g; the bias half's quantile is
widened by the mean ``phi_b`` its statistic shows on the calibration recording (the model's own
error along the turn is a bias too). A calibration whose recording shows such a bias beyond
white noise's sampling error (the ring jig), or whose ADC is too little dithered by the analog
noise to be unbiased at standstill, keeps the chi-square half alone. The wrong locks left sit
within a third of a noise sigma of the wrong curve: at k = 96 that is within the healthy spread
of any test, and only more samples (a later lock for some healthy power-ups) would tell.

Units: angles in rad (mechanical unless said electrical); d, rho, zeta in the sensor's unit;
costs in noise-sigma units squared.
"""

from __future__ import annotations

# The decoder and its analysis live in two private modules (the seam: what runs at power-up,
# and what a calibration states about it); their public names are this module's.
from hallcal.sensor._absolute_analysis import (
    Identifiability,
    IdentifiabilityReason,
    IdentifiabilityReport,
    NoiseEstimate,
    analyze_calibration,
    assess_identifiability,
    estimate_normal_noise,
    gate_dispersion,
)
from hallcal.sensor._absolute_analysis import SeparationMap as SeparationMap
from hallcal.sensor._absolute_analysis import bias_dispersion as bias_dispersion
from hallcal.sensor._absolute_analysis import separation_map as separation_map
from hallcal.sensor._absolute_analysis import standstill_error as standstill_error
from hallcal.sensor._absolute_analysis import standstill_error_rate as standstill_error_rate
from hallcal.sensor._absolute_decoder import DEFAULT_COST_CAP as DEFAULT_COST_CAP
from hallcal.sensor._absolute_decoder import DEFAULT_ERROR_TARGET as DEFAULT_ERROR_TARGET
from hallcal.sensor._absolute_decoder import DEFAULT_GAIN_SD as DEFAULT_GAIN_SD
from hallcal.sensor._absolute_decoder import DEFAULT_GATE_RATE as DEFAULT_GATE_RATE
from hallcal.sensor._absolute_decoder import DEFAULT_GATE_SAMPLES as DEFAULT_GATE_SAMPLES
from hallcal.sensor._absolute_decoder import (
    DEFAULT_INTERPOLATION_TOLERANCE as DEFAULT_INTERPOLATION_TOLERANCE,
)
from hallcal.sensor._absolute_decoder import DEFAULT_LOCK_TRAVEL as DEFAULT_LOCK_TRAVEL
from hallcal.sensor._absolute_decoder import GRID_CHOICES as GRID_CHOICES
from hallcal.sensor._absolute_decoder import TWO_PI as TWO_PI
from hallcal.sensor._absolute_decoder import (
    AbsoluteAngles,
    PowerUpDecoder,
    PowerUpIdentification,
    PowerUpIdentifier,
    PowerUpStatus,
    absolute_reconstruction,
    build_decoder,
    null_vector,
)
from hallcal.sensor._absolute_decoder import gain_terms as gain_terms
from hallcal.sensor._absolute_decoder import gram_at as gram_at
from hallcal.sensor._absolute_decoder import tangent_terms as tangent_terms

__all__ = [
    "AbsoluteAngles",
    "Identifiability",
    "IdentifiabilityReason",
    "IdentifiabilityReport",
    "NoiseEstimate",
    "PowerUpDecoder",
    "PowerUpIdentification",
    "PowerUpIdentifier",
    "PowerUpStatus",
    "absolute_reconstruction",
    "analyze_calibration",
    "assess_identifiability",
    "build_decoder",
    "estimate_normal_noise",
    "gate_dispersion",
    "null_vector",
]
