"""Every threshold of the diagnosis, in one place, with the reason for each (docs/decisions/0009).

Units: gains are fractions of the validation rmse, times in s, ratios are dimensionless.
"""

from __future__ import annotations

#: An effect must lower the validation rmse by more than this fraction. Below 10 % a refit with a
#: few more parameters buys as much on held-out rows by chance on the suites' noise levels.
MIN_GAIN = 0.10

#: Block tests of the validation error (hilbench/diagnosis/significance.py): p below this. Blocks (not
#: samples) because residuals are strongly autocorrelated; 1 % because every diagnosis tests up to
#: ten candidates and a false effect costs the user a wrong model.
P_MAX = 0.01

#: The fewest contiguous validation blocks of the tests: enough for p < 0.01 to be reachable by the
#: signed ranks (needs at least 7 of 7); a short record gets this many even when they are shorter
#: than SUM_TEST_BLOCK_CORRELATIONS correlation lengths.
N_BLOCKS = 20

#: The tests use blocks this many correlation lengths of the squared-error difference long: at 1/e
#: per length neighbours share under 5 % of their variance, so the block differences are nearly
#: independent and their signs exchangeable under no effect (decisions 0022, 0032) ...
SUM_TEST_BLOCK_CORRELATIONS = 10
#: ... at least N_BLOCKS and at most this many (more blocks add resolution the flips cannot use) ...
SUM_TEST_MAX_BLOCKS = 200
#: ... and this many random sign flips: p resolves to 1e-4, far below P_MAX.
SUM_TEST_FLIPS = 10000

#: The current validation rmse must exceed the noise floor by more than the floor's own uncertainty
#: (an error at the sensor's noise has nothing left to explain), and at most by this multiple of it
#: when that uncertainty is larger or unknown (verdict.error_above_noise, decision 0045). The floor is
#: the sensor's, estimated from the measured output (hilbench/diagnosis/noise.py), not from the
#: model's residual, which fast model error inflates.
NOISE_FACTOR = 1.5

#: A noise estimate counts only when it rests on this many samples: the robust std of n samples
#: scatters by ~1.2/sqrt(n) (8 % at 200), and the floor is the smallest estimate, which scatter biases low.
NOISE_MIN_SAMPLES = 200
#: Difference orders of the noise estimate: order k cancels polynomials of degree < k; higher orders
#: amplify fast signal content (2 sin(pi f / fs))^k more than they cancel trends.
NOISE_DIFFERENCE_ORDERS = (1, 2, 3, 4)
#: Holds count for the noise estimate after this time: a delay or a resonance settles first.
NOISE_HOLD_SETTLE_S = 0.1

#: A real effect is learned on one set of rows and holds on unseen rows: the validation gain must be
#: at least this fraction of the training gain (else: more parameters, not physics) ...
AGREE_VALIDATION_OVER_TRAIN = 0.5
#: ... or, on the validation rows, the mean square the refit removed is at least this fraction of the
#: mean square of its change there (1: the change is error removed; -1: unrelated to the error; 0.5:
#: the error held three quarters of the change), so validation rows that hold less of the effect
#: than training's still confirm it (decision 0033) ...
AGREE_CHANGE_EXPLAINED = 0.5
#: ... and the training gain at least this fraction of the validation gain (else: chance extrapolation).
AGREE_TRAIN_OVER_VALIDATION = 0.25

#: With a rate plan, training may not get worse than this fraction (the calibrated shape is fixed).
TRAINING_WORSE_TOLERANCE = 0.01

#: creep is significant only if the residual drifts along holds (after the first CREEP_SETTLE_S of
#: each hold) by this fraction of its rms: the physical signature, which a refit alone can fake (the
#: creep low-pass also buys phase lag on delay or dynamics data) ...
CREEP_MIN_DRIFT = 0.2
#: ... or, where other errors fill the rms, by at least this many standard errors the sensor's noise
#: leaves on a drift ...
CREEP_MIN_DRIFT_OVER_NOISE = 3.0
#: ... and the creep refit removes at least this fraction of that drift (most of it): another slow
#: cause along holds (a ringing, a temperature or load change) leaves most of its drift to creep's
#: refit (decision 0059).
CREEP_MIN_DRIFT_REMOVED = 0.5
#: A delay or a resonance settles within this time after a step; creep keeps drifting after it.
CREEP_SETTLE_S = 0.1
#: Creep is testable only if the input holds still at least this long somewhere.
CREEP_MIN_HOLD_S = 0.2

#: A form of an effect chosen on an inner split: the first INNER_SPLIT of the training rows fit,
#: the rest judge; the richer form must lower that error by RICHER_FORM_MARGIN.
INNER_SPLIT = 0.8
RICHER_FORM_MARGIN = 0.1
#: Validation drives beyond training's largest |input| when it reaches more than REACH_MARGIN past
#: it; within that a memoryless polynomial is not extrapolated and its order is chosen as any
#: effect's form (decision 0069). 2 %: a v^4 grows by 8 % of its top value there.
REACH_MARGIN = 0.02
#: When no row of validation finds an effect, the rows within training's input reach are judged
#: alone (decision 0071): the envelope widens training's input range by REACH_ENVELOPE of its span,
#: and the rows left must be at least REACH_MIN_KEPT of validation's (decision 0055's values).
REACH_ENVELOPE = 0.05
REACH_MIN_KEPT = 0.25
#: A loop family is judged on an inner split only when the inner fit's rows turn the input this
#: many times (two turns close a loop): rows that only step and hold show no loop shape to learn.
INNER_MIN_REVERSALS = 2

#: The rate forms are compared on held-back rows whose drive frequency lies within the inner fit's
#: own, widened by this factor for the turning-point estimator's jitter (decision 0050).
INNER_RATE_TOLERANCE = 1.05

#: The base refitted from a significant candidate's shape replaces the base when it fits the
#: training rows better by more than this fraction (hilbench/diagnosis/base_polish.py): below it
#: the two are the same optimum reached again, up to the search's tolerance.
POLISH_MIN_TRAIN_GAIN = 0.01

#: A tie on validation error is broken by the residual's pattern when signatures differ this much.
SIGNATURE_MARGIN = 0.2

#: The signature of a confusable pair (hilbench/diagnosis/confusable.py) speaks only where the
#: difference it measures stands this many standard errors clear of zero (about 1 in 370 by chance
#: for a normal statistic): the ends' parity of saturation against asymmetry, the change of the
#: equivalent lag with the input rate of rate-dependence against a delay.
CONFUSABLE_Z = 3.0

#: Two refits are never tied when the leader's validation mean square is below the other's by this
#: factor, whatever the block tests say: a gain concentrated in a few blocks (a knee at the largest
#: drive) leaves them little power (hilbench/diagnosis/significance.py), and half the error is not
#: a coin toss for the residual's pattern to settle. On an output knee, for example, the
#: saturation refit validated at 0.55 um against an even term's 1.04 (p 0.013) and the even
#: pattern put the even term first; the patterns' reorders of 600 development cases were between
#: refits within 4 % in rmse (decision 0047).
TIE_MEAN_SQUARE_RATIO = 2.0

#: A tie the patterns do not break goes to the candidate with fewer free parameters only when its
#: validation rmse is within this fraction of the leader's: equal errors, not merely errors the
#: block test cannot separate (a saturation explaining 39 % against an even term's 31 % is a
#: difference the few blocks miss, not an equality).
PARSIMONY_MARGIN = 0.05
#: ... and only when the candidate with fewer parameters fits the training rows nearly as well: a
#: leader whose training rmse is below the simpler one's by more than this factor did not match it
#: by flexibility (a parameter or two more buy percents, not multiples; a resonance near the drive
#: trains at 0.22 um where a delay stops at 1.46), as the wrong-base check asks multiples.
PARSIMONY_TRAINING_RATIO = 2.0

#: An auxiliary channel is tried when its smoothed range exceeds this many noise stds: pure noise
#: gives well under 1, a 1.5 degC drift under 0.15 degC of noise gives 10.
AUX_MIN_VARIATION = 3.0

#: A drive rings the dynamics at one rate when its input excites (input_motion.excited_bandwidth_hz)
#: at least this multiple of its highest drive frequency: a triangle's corners reach ~30x (its
#: harmonics fall as 1/k^2), a sine's content ends at 1x. Issue 11 item 3a: a 10 Hz triangle
#: identifies a 350 Hz resonance, a 10 Hz sine does not.
HARMONIC_REACH = 5.0

#: Drive frequencies count as several when the spread (highest over lowest half-cycle frequency
#: in time percentiles) reaches this ratio.
SEVERAL_RATES_SPREAD = 1.5

#: The base may be the wrong family only when the validation error exceeds this many noise floors:
#: near the noise the loop shape is right enough and refitting every family would cost for nothing.
WRONG_BASE_NOISE_FACTOR = 10.0
#: Another base is suggested when it lowers the validation rmse by this factor: effects on a
#: base of the right family give tens of percent; a wrong loop shape costs multiples.
WRONG_BASE_RATIO = 2.0

#: Effects that overlap (creep after each load step) are tried in pairs when no single effect is
#: significant or the best one lowers the validation rmse by less than this fraction (it leaves most
#: of the error) ...
PAIR_TRIGGER_GAIN = 0.5
#: ... among the singles with the best gains (training or validation; one of each pair over MIN_GAIN in
#: training): the top PAIR_MAX_MEMBERS (3 members, at most 3 pairs), and the single that carries over
#: best when they leave it out (decision 0048: at most 4 members, 6 pair refits).
PAIR_MAX_MEMBERS = 3

#: Forms of an effect chosen on the training fit (saturation's) whose training rmse is above the
#: best form's by less than this fraction of what the best form lowers it by (from the base's) fit
#: the rows equally: the one with the fewest free parameters is chosen (decision 0043). Copies of
#: every hysteresis column with their own weights trained 0.005 % of the gain better than the
#: one-weight Wiener knee and validated 6x worse: free weights fit the noise, not the knee.
FORM_TIE = 0.01

#: The order of the two leading effects is checked on a finer base (diagnosis/resolution.py, decision
#: 0060) with this many times the base's default operators: at 2x an even v^4 on a one-sided play rig
#: still ranked behind a saturation, at 3x it reached the noise and led (decision 0054's table).
RESOLUTION_FACTOR = 3
#: ... and for ``pmpi``, whose operators each carry a searched eta, this many times: at 30 operators
#: the search over 29 etas stopped short of the 20-operator fit (two cases of a delay and a lag
#: under ``pmpi``: the lag validated 0.85 against 0.30 um, the delay 0.19 against 0.14), so the
#: finer base would be a worse fit, not a finer one (decision 0068).
PMPI_RESOLUTION_FACTOR = 2

#: The structure with the hysteresis inside the mechanics is tried only on a resonance: second-order
#: dynamics whose magnitude peaks, zeta below 1/sqrt(2) (hilbench/diagnosis/structure_check.py) ...
MECHANICS_MAX_ZETA = 1.0 / 2.0**0.5
#: ... that the drive excites: this share of the input's power within an octave of the natural
#: frequency (a broadband drive across it puts tens of percent there, 0.42 on the Bouc-Wen
#: benchmark's 5-150 Hz multisine around 40 Hz; a triangle's corners ringing a resonance 30 times
#: faster ~1e-4; below resonance the oscillator is its static map, decision 0103).
MECHANICS_DRIVE_SHARE = 0.1
