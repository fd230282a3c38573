"""Paper 000 (FPMPI + online identification of a GMA), sec. 2.3: the actuator under a placed load and cooling.

The procedure (Fig. 4 and 5): a 4 Hz, 2.5 A peak-to-peak sine while a 10 kg weight is placed on the
output disk (``gmm-fpmpi-load``, load cell recorded), and a 6 Hz, 1.5 A peak-to-peak sine while the
actuator cools from 42.5 degC (``gmm-fpmpi-temperature``, thermometer recorded). The loops move and
change shape with the load and the temperature; an offline FPMPI model fitted on the first 70 % of
each run misses it on the last 30 %, and the same model with the recorded channel as an effect
(``+load``, ``+temperature``: offset and gain proportional to the channel) follows it. The rig's
40 Hz dynamics appear at 4-6 Hz as a phase lag, taken here by ``delay`` (``dynamics`` fits slower). This is what
paper 000's online identifier (OIIR) tracks without a sensor; here the offline fits show the size of
the change.

The script takes either rig with ``--rig`` and opens the other itself. Shortened: the paper's 14 min
of cooling is cut to 120 s (about 1.3 degC, ``--quick``: 20 s) and the load run to its 5 s; the
temperature effect is the same per degree.

Run: ``hilbench run experiments/paper-000-load-temperature.py --rig gmm-fpmpi-load``
"""

from hilbench.runners.script import Bench, current_bench

RIG = "gmm-fpmpi-load"
bench: Bench = current_bench()  # the bench `hilbench run` gives the script (also a global named bench)

rigs = {"load": "gmm-fpmpi-load", "temperature": "gmm-fpmpi-temperature"}
if bench.config.name not in rigs.values():
    bench.log(f"note: rig {bench.config.name!r} is neither of {sorted(rigs.values())}; the built-in ones are used")
benches = {}
for channel, name in rigs.items():
    benches[channel] = bench if bench.config.name == name else bench.open_rig(name)

cooling_s = 20.0 if bench.quick else 120.0
plans = {
    "load": "sine:amplitude=1.25,offset=1.25,phase_deg=-90,frequency_hz=4,duration_s=5",  # Fig. 4
    "temperature": f"sine:amplitude=0.75,offset=0.75,phase_deg=-90,frequency_hz=6,duration_s={cooling_s:g}",  # Fig. 5
}

found = {}
for channel, b in benches.items():
    sweep = b.sweep(plans[channel], f"{channel}.h5", label=f"{channel}-sine")
    without = b.fit(sweep, "fpmpi+delay")
    with_channel = b.fit(sweep, f"fpmpi+delay+{channel}")
    before, after = without.metrics["validation"]["rmse"], with_channel.metrics["validation"]["rmse"]
    run = b.runs(sweep)[-1]
    span = float(run.aux[channel].max() - run.aux[channel].min())
    bench.log(f"{b.config.name}: {channel} spans {span:.2f} {'N' if channel == 'load' else 'degC'}; validation rmse "
              f"fpmpi+delay {before:.3f} um -> +{channel} {after:.3f} um")
    found[channel] = {"rig": b.config.name, "span": span, "rmse_without_um": before, "rmse_with_um": after,
                      "recording": str(sweep.file)}
bench.report(**found)
