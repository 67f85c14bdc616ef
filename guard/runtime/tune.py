"""guard tune: the noise model fitted to a vehicle's own clean logs, written as a profile for --config.

    guard tune clean1.bin clean2.tlog ... --out my-vehicle.toml [--config base.toml]

Every sensor's innovations, normalised by their covariance (z = r_i / sqrt(S_ii)), have unit variance
when the model fits. From logs without an attack, guard tune fits, in this order:
1. the receiver's latency (`filter.gnss_delay_s`): the delay in DELAYS that leaves the GNSS innovations
   smallest (a latency shows in turns and speed changes);
2. each sensor's noise floor: scaled until its innovations' standard deviation over all the logs is
   1 / MARGIN of the model's (the noise set MARGIN above what the logs show), within BOUNDS of the
   defaults; a few passes, as the filter's own uncertainty is part of each innovation's. The
   standard deviation is the larger of the samples' and their wander's: the spread of their means
   over blocks of guard.core.longrun.BLOCK samples, scaled to one sample's (a real copter's compass
   or receiver sits well inside its model sample by sample while its mean over a second wanders,
   and a CUSUM sums the wander: fitted to the samples alone, the noise came out smaller and the
   same logs raised more alarms with the profile than without it). On wheels the sideways
   constraint, tested with the accelerometer, is fitted apart (`lateral_sigma_mps`). The position's
   wander is fitted apart too, as the random walk by which the filter follows the receiver's slow
   error (`q_pos_m`, `position_walk`), its floor to the samples' spread alone. A fix whose
   course the receiver held is left out (Innovation.modelled): its innovation is the held course's
   error, the same fix after fix, not the receiver's noise (taken in, it read as a wander, and a slow
   car's receiver's velocity floor came out over three times its own);
3. the compass's offset (`filter.mag_offset_rad`) and, on wheels, their slip (`filter.slip_rad_per_mps2`)
   and how far ahead of the axle the sensors sit (`filter.sensors_ahead_m`): what the filter learnt,
   averaged over the logs; the compass's offset with the motors still, less what it moved in the
   windows after the motors started or stopped (guard.core.aiding.motors), which each flight learns
   anew;
4. how poor the receiver usually says it is (`filter.gnss_h_acc_usual_max_m`, `gnss_vel_acc_usual_max_mps`):
   USUAL_MARGIN times the worst of its usual figures over the logs (guard.core.aiding.receiver,
   `UsualWorst`), so that in flight the cap on its figures follows a receiver that turns poor only
   that far and a spoofer who raises its claims slowly cannot blunt its tests; left unset for a
   receiver that reports none;
5. whether one noise level fits every flight: if any one log's innovations, on any sensor, pass
   the tuned model (a factor over 1) and its test comes within NEAR of its threshold (`unfitted`),
   it does not, and the profile lets each test widen in flight by the wander it measures
   (`monitor.max_wander_factor` = guard.core.longrun.F_MAX; learnt slowly and only while every test
   is calm). The cost is said: on a flight that wanders, an attack is caught later by as much. On
   7 held-out real copter flights (README, "Real flights never tuned on") it took the tuned profile
   from 13 alarms to 6, and a 2 m step written into their fixes from 3 of 21 caught to 1, the
   accelerometer's bias from 8 to 4.
Then it replays the logs with the profile and prints each one's margin: the largest statistic over its
threshold per sensor (1.0 is an alarm). The profile is what it fitted; the file it writes holds that
and, so that it works alone with --config, the settings of the config it started from that differ
from guard's defaults (a vehicle set to "ground" changes the fit, and a file that dropped it would
run another model than the one tuned).
Logs that hold an attack, or a sensor fault, would teach guard to accept it: give clean ones. A log whose
receiver's position wanders from its own velocity further than the largest walk tune fits (a fault or
a spoof: guard.runtime.position_wander.beyond_tune, against the model the tuning starts from, measured in
the first latency's replays) is named, as it is tuned on.

Each step replays every log once (the latency's, every log at every delay; the first noise pass takes
the latency's replays at the delay it chose, the same config), 10 or 11 replays of each log in all;
they are independent, so `jobs` processes share them (`guard tune --jobs`, every core by default;
`Replays`). The profile is the same whatever the number: each replay is the same and the
logs' innovations are summed in the logs' order.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import tomli_w

from guard.config import Config, table
from guard.core.aiding.imu import lateral_rows
from guard.core.aiding.receiver import USUAL_MARGIN, UsualWorst
from guard.core.ekf import BM, KS, LA, Q_POS_MAX, FilterConfig
from guard.core.longrun import BLOCK, F_MAX, BlockMeans, normalised
from guard.errors import GuardError
from guard.model.events import Estimate, Tested
from guard.model.samples import GnssFix
from guard.model.sensors import Sensor
from guard.runtime.position_wander import SAY_LAG_S, PositionWander, beyond_tune
from guard.runtime.replay import replay
from guard.sinks.base import Sink

DELAYS = (0.0, 0.05, 0.1, 0.15, 0.2, 0.25)
MARGIN = 1.25           # the fitted noise is this much above what the logs show
BOUNDS = (0.5, 20.0)    # a floor is scaled within these factors of its default
PASSES = 3
MIN_BLOCKS = 10         # block means (times channels) before the wander is taken
NEAR = 0.7              # a tuning log's test this near its threshold, on a sensor the model does not fit
LATERAL = "lateral"     # on wheels, the accelerometer's third channel: the sideways constraint, fitted apart
# the configuration keys each sensor's noise scales
KEYS: dict[str, tuple[str, ...]] = {
    Sensor.GNSS_POS: ("gnss_pos_sigma_m", "gnss_pos_unreported_m"),
    Sensor.GNSS_VEL: ("gnss_vel_sigma_mps", "gnss_vel_unreported_mps"),
    Sensor.MAG: ("heading_sigma_rad",),
    Sensor.GYRO: ("gyro_sigma_radps",),
    Sensor.ACCEL: ("accel_sigma_mps2",),
    LATERAL: ("lateral_sigma_mps",),
}


def parts(sensor: Sensor, z) -> list[tuple[str, object]]:
    """A tested innovation's channels by the keys that scale them: a ground vehicle's accelerometer
    test holds the sideways constraint's too, whose noise is its own (`lateral_sigma_mps`)."""
    own, lateral = lateral_rows(sensor, len(z))
    return [(sensor, z[own])] + ([(LATERAL, z[lateral])] if lateral is not None else [])


def tested_by(key: str) -> Sensor:
    """The sensor whose test (and largest statistic) a key's channels are in."""
    return Sensor.ACCEL if key == LATERAL else Sensor(key)


class Innovations(Sink):
    """Sums of z^2 of the fused innovations per sensor, and the compass offset the filter ended with."""

    def __init__(self):
        self.sum: dict[str, float] = {}
        self.n: dict[str, int] = {}
        self.block: dict[str, BlockMeans] = {}
        self.wander: dict[str, float] = {}   # sum over closed blocks and channels of BLOCK zbar^2
        self.blocks: dict[str, int] = {}
        self.mag_offset: float | None = None
        self.slip: float | None = None
        self.ahead: float | None = None

    def on_events(self, events) -> None:
        for e in events:
            if isinstance(e, Tested) and e.innovation.fused and e.innovation.modelled:
                i = e.innovation
                for s, z in parts(i.sensor, normalised(i.r, i.S)):
                    self.sum[s] = self.sum.get(s, 0.0) + float(z @ z)
                    self.n[s] = self.n.get(s, 0) + len(z)
                    closed = self.block.setdefault(s, BlockMeans()).add(z)
                    if closed is not None:
                        zbar = closed[0]
                        self.wander[s] = self.wander.get(s, 0.0) + BLOCK * float(zbar @ zbar)
                        self.blocks[s] = self.blocks.get(s, 0) + len(z)
            elif isinstance(e, Estimate):
                self.mag_offset = float(e.x[BM])
                self.slip = float(e.x[KS])
                self.ahead = float(e.x[LA])

    def factor(self, sensor: Sensor) -> float | None:
        """The innovations' standard deviation over the model's: the samples', or their wander's
        where that is larger (over at least MIN_BLOCKS blocks)."""
        spread = self.spread(sensor)
        return None if spread is None else max(spread)

    def spread(self, sensor: Sensor) -> tuple[float, float] | None:
        """(the samples' standard deviation, their wander's) over the model's; the wander 0 over fewer
        than MIN_BLOCKS blocks. None over fewer than 50 samples."""
        n = self.n.get(sensor, 0)
        if n < 50:
            return None
        blocks = self.blocks.get(sensor, 0)
        wander = self.wander[sensor] / blocks if blocks >= MIN_BLOCKS else 0.0
        return math.sqrt(self.sum[sensor] / n), math.sqrt(wander)


class Figures(Sink):
    """A log's receiver: its worst usual accuracy figures (UsualWorst), and how far its position wanders
    from its own velocity against the model (guard.runtime.position_wander)."""

    def __init__(self, filter_cfg: FilterConfig | None = None):
        self.worst = UsualWorst()
        self.wander = PositionWander(filter_cfg)

    def on_sample(self, sample) -> None:
        if isinstance(sample, GnssFix):
            self.worst.hear(sample)
            self.wander.on_sample(sample)


def faulty(logs: list[str], figures: list[Figures]) -> list[str]:
    """What to say of each log whose receiver wanders from its own velocity further than the largest walk
    tune fits allows (position_wander.beyond_tune): a fault or a spoof in a log given as clean."""
    out = []
    for log, fig in zip(logs, figures):
        got = fig.wander.measure((SAY_LAG_S,))
        if beyond_tune(got):
            at = got["lags"][0]
            out.append(f"{Path(log).name}: its receiver's position wanders {at['wander_m']:.2f} m over {SAY_LAG_S:g} s "
                       f"from its own velocity, past the largest walk guard tune fits ({at['tunable_m']:.2f} m): "
                       "a fault or a spoof, not its usual wander; a profile tuned on it has a blunter position test "
                       "(give clean logs)")
    return out


def usual_max(figures: list[Figures]) -> dict[str, float]:
    """The profile's keys for the receiver's usual figures: USUAL_MARGIN times the worst over the logs,
    each only where some log's receiver reported it."""
    out = {}
    for i, key in enumerate(("gnss_h_acc_usual_max_m", "gnss_vel_acc_usual_max_mps")):
        heard = [w for f in figures if (w := f.worst.worst()[i]) is not None]
        if heard:
            out[key] = max(round(USUAL_MARGIN * max(heard), 3), 0.001)     # never 0, which means "unknown"
    return out


def position_walk(spread: tuple[float, float], q_pos: float, q_default: float) -> tuple[float, float]:
    """The position's fit: (the factor its noise floors scale by, its random walk q_pos_m). A receiver's
    position error is mostly slow, its fix-to-fix noise small (the Erle copters' innovations: 0.3 of
    the default floor sample by sample, 1.2 of it in their means over 40 fixes): the wander is taken
    into the random walk the filter follows it by, and the floor is scaled to the samples' spread
    alone. The walk is raised by the wander's factor, squared: the spread of the means falls about as
    1 / sqrt(q) (measured on those copters: q times 2.2, their wander 1.19 -> 0.79). Without MARGIN:
    the floor keeps its margin, and a walk raised past the wander follows a ramp as well (with the
    margin, 0.22 against 0.16 here, the held-out flights' 1 m/s ramp was caught in 15 of 21 runs
    against 18, for the same alarms). It is never lowered (a wander within the model leaves it) and
    goes up to Q_POS_MAX times the default; where that bound holds it, the wander it cannot take goes
    into the floor as before. Taken into the floor, as the other sensors' wander is, it blunted every
    position test: a 5 m step written into 7 held-out Erle flights was caught in 3 of 21 runs with
    their profile, against 19 with the defaults (README, "Real flights never tuned on")."""
    per_sample, wander = spread
    raised = q_pos * max(1.0, wander) ** 2
    hi = max(q_default * Q_POS_MAX, q_pos)
    if raised > hi:
        return max(per_sample, wander), hi
    return per_sample, raised


def with_filter(cfg: Config, **changes) -> Config:
    flt = dataclasses.replace(cfg.monitor.filter, **changes)
    return dataclasses.replace(cfg, monitor=dataclasses.replace(cfg.monitor, filter=flt))


def replay_one(job: tuple[str, Config, bool]) -> tuple[Innovations, Figures | None, dict]:
    """One log replayed with cfg: its innovations, its receiver's figures (if asked) and its report."""
    log, cfg, with_figures = job
    one, fig = Innovations(), (Figures(cfg.monitor.filter) if with_figures else None)
    report = replay(log, cfg, listeners=[one] if fig is None else [one, fig])
    return one, fig, report


def default_jobs() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


class Replays:
    """Logs replayed in `jobs` processes (1: in this one), each replay's results in the order asked."""

    def __init__(self, jobs: int = 1):
        self.jobs = max(1, jobs)
        self._pool: ProcessPoolExecutor | None = None

    def run(self, work: list[tuple[str, Config, bool]]) -> list:
        """replay_one of each (log, cfg, with_figures), in that order."""
        if self.jobs == 1 or len(work) < 2:
            return [replay_one(w) for w in work]
        if self._pool is None:
            self._pool = ProcessPoolExecutor(self.jobs)
        return list(self._pool.map(replay_one, work))

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None


def measure(logs: list[str], cfg: Config, each: list | None = None, figures: list | None = None,
            replays: Replays | None = None) -> tuple[Innovations, list[dict]]:
    """Replay every log with cfg; the innovations of all of them, and each one's report (and each
    one's innovations into `each`, its receiver's figures into `figures`, if given)."""
    return pooled((replays or Replays()).run([(log, cfg, figures is not None) for log in logs]), each, figures)


def pooled(results: list, each: list | None = None, figures: list | None = None) -> tuple[Innovations, list[dict]]:
    """The logs' replays (replay_one's, in the logs' order) summed: the innovations of all of them and
    each one's report (each one's innovations into `each`, its figures into `figures`, if given)."""
    sink, reports = Innovations(), []
    offsets, slips, aheads = [], [], []
    for one, fig, report in results:
        reports.append(report)
        if each is not None:
            each.append(one)
        if figures is not None:
            figures.append(fig)
        for s in one.sum:
            sink.sum[s] = sink.sum.get(s, 0.0) + one.sum[s]
            sink.n[s] = sink.n.get(s, 0) + one.n[s]
        for s in one.blocks:
            sink.wander[s] = sink.wander.get(s, 0.0) + one.wander[s]
            sink.blocks[s] = sink.blocks.get(s, 0) + one.blocks[s]
        if one.mag_offset is not None:
            still = report.get("compass_offset_still_rad")     # less what the motors' current turned
            offsets.append(one.mag_offset if still is None else still)
            slips.append(one.slip)
            aheads.append(one.ahead)
    sink.mag_offset = sum(offsets) / len(offsets) if offsets else None
    sink.slip = sum(slips) / len(slips) if slips else None
    sink.ahead = sum(aheads) / len(aheads) if aheads else None
    return sink, reports


def unfitted(logs: list[str], each: list[Innovations],
             reports: list[dict]) -> list[tuple[float, str, str, float]]:
    """(factor, log name, sensor, largest statistic/threshold) for each log and sensor that the tuned
    model does not fit (its innovations over the model, a factor over 1) and whose test shows it (its
    largest statistic/threshold NEAR or more, replayed with the tuned model): a flight that one noise
    level, fitted to all the logs, leaves near an alarm. Both, as a log's factor alone moves with
    chance on a short log (a receiver's error correlated over a minute leaves few independent
    blocks), and a sensor far from its threshold needs nothing."""
    return [(f, Path(log).name, sensor, peak) for log, one, r in zip(logs, each, reports) for sensor in KEYS
            if (f := one.factor(sensor)) is not None and f > 1.0
            and (peak := r["peak_ratio"].get(tested_by(sensor).value, 0.0)) >= NEAR]


def gnss_z2(sink: Innovations) -> float:
    n = sum(sink.n.get(s, 0) for s in (Sensor.GNSS_POS, Sensor.GNSS_VEL))
    return sum(sink.sum.get(s, 0.0) for s in (Sensor.GNSS_POS, Sensor.GNSS_VEL)) / max(n, 1)


def tune(logs: list[str], base: Config, say: Callable[[str], None] = print, jobs: int = 1) -> tuple[dict, Config]:
    """The profile (section -> key -> value, what differs from base) and the tuned config; the logs
    replayed on `jobs` processes."""
    for log in logs:
        if not Path(log).is_file():
            raise GuardError(f"{log}: no such file")
    replays = Replays(min(jobs, len(logs) * len(DELAYS)))
    try:
        return _tune(logs, base, say, replays)
    finally:
        replays.close()


def _tune(logs: list[str], base: Config, say: Callable[[str], None], replays: Replays) -> tuple[dict, Config]:
    # 1. the receiver's latency: every delay's replays at once
    results = replays.run([(log, with_filter(base, gnss_delay_s=delay), delay == DELAYS[0])
                           for delay in DELAYS for log in logs])
    # each log's receiver, heard once (its figures do not depend on the config): a receiver that wanders
    # past the largest walk tune fits, against the model the tuning starts from, and its usual figures (4.)
    figures: list[Figures] = [fig for _, fig, _ in results[:len(logs)]]
    for line in faulty(logs, figures):
        say(line)
    scores = []
    for i, delay in enumerate(DELAYS):
        sink, _ = pooled(results[i * len(logs):(i + 1) * len(logs)])
        scores.append((gnss_z2(sink), delay))
        say(f"latency {delay:.2f} s: GNSS innovations {math.sqrt(scores[-1][0]):.2f}x the model")
    best = scores.index(min(scores))
    cfg = with_filter(base, gnss_delay_s=DELAYS[best])
    # 2. each sensor's noise; the first pass's replays are the latency's at the delay taken (the same config)
    defaults = FilterConfig()
    for n in range(PASSES):
        sink, _ = pooled(results[best * len(logs):(best + 1) * len(logs)]) if n == 0 else \
            measure(logs, cfg, replays=replays)
        changes = {}
        for sensor, keys in KEYS.items():
            f = sink.factor(sensor)
            if f is None:
                continue
            if sensor == Sensor.GNSS_POS:
                f, changes["q_pos_m"] = position_walk(sink.spread(sensor), cfg.monitor.filter.q_pos_m,
                                                      defaults.q_pos_m)
            for key in keys:
                lo, hi = (getattr(defaults, key) * b for b in BOUNDS)
                changes[key] = min(max(getattr(cfg.monitor.filter, key) * f * MARGIN, lo), hi)
        cfg = with_filter(cfg, **changes)
    # 3. the compass's offset
    sink, reports = measure(logs, cfg, replays=replays)
    if sink.mag_offset is not None:
        # an air vehicle's slip and lever arm are never learnt: they stay where they started, and the
        # profile leaves them out
        cfg = with_filter(cfg, mag_offset_rad=sink.mag_offset, slip_rad_per_mps2=min(max(sink.slip, 0.0), 0.05),
                          sensors_ahead_m=min(max(sink.ahead, -3.0), 3.0))
    # 4. how poor the receiver usually says it is
    usual = usual_max(figures)
    if usual:
        cfg = with_filter(cfg, **usual)
        said = [f"h_acc {usual['gnss_h_acc_usual_max_m'] / USUAL_MARGIN:.2f} m"] \
            if "gnss_h_acc_usual_max_m" in usual else []
        said += [f"vel_acc {usual['gnss_vel_acc_usual_max_mps'] / USUAL_MARGIN:.2f} m/s"] \
            if "gnss_vel_acc_usual_max_mps" in usual else []
        say(f"receiver: its usual figures at worst {' and '.join(said)}; believed up to {USUAL_MARGIN:g} times "
            "that in flight, no further")
    else:
        say("receiver: it reports no accuracy figures in these logs; nothing fitted of what it may say of itself")
    for sensor in KEYS:
        f = sink.factor(sensor)
        if f is not None:
            say(f"{sensor}: innovations {f:.2f}x the tuned model")
    # 5. whether one noise level fits every flight
    each: list[Innovations] = []
    overall, reports = measure(logs, cfg, each, replays=replays)
    over = unfitted(logs, each, reports)
    if len(logs) == 1:
        say("one log: whether one noise level fits every flight of this vehicle cannot be told from it; "
            "give guard tune two or more clean flights")
    widen = bool(over) and cfg.monitor.max_wander_factor < F_MAX
    if widen:
        f, name, sensor, peak = max(over)
        say(f"{name}: {sensor} innovations {f:.2f}x the tuned model ({overall.factor(sensor):.2f}x over all the "
            f"logs), its test at {peak:.2f} of its threshold: one noise level does not fit every flight, so "
            f"each test widens in flight by the wander it measures, up to {F_MAX:g}x "
            "(monitor.max_wander_factor); on a flight that wanders an attack is caught later by as much")
        cfg = dataclasses.replace(cfg, monitor=dataclasses.replace(cfg.monitor, max_wander_factor=F_MAX))
        _, reports = measure(logs, cfg, replays=replays)
    for log, r in zip(logs, reports):
        margin = ", ".join(f"{s} {v:.2f}" for s, v in sorted(r["peak_ratio"].items()))
        say(f"{Path(log).name}: {len(r['alarms'])} alarm(s); largest statistic/threshold: {margin or 'none'}")
    tuned, was = cfg.monitor.filter, base.monitor.filter
    profile = {"filter": {f.name: round(getattr(tuned, f.name), 6) for f in dataclasses.fields(FilterConfig)
                          if getattr(tuned, f.name) != getattr(was, f.name)}}
    if widen:
        profile["monitor"] = {"max_wander_factor": cfg.monitor.max_wander_factor}
    return profile, cfg


def self_contained(profile: dict, cfg: Config) -> dict:
    """What a file must hold for `--config` alone to give cfg: every key whose value differs from
    guard's built-in defaults (the config tune started from included: a vehicle set to "ground", a
    link), and the profile's own keys as tune rounded them."""
    have, defaults = table(cfg), table(Config())
    out = {section: {k: v for k, v in keys.items() if v != defaults[section][k]} for section, keys in have.items()}
    for section, keys in profile.items():
        out.setdefault(section, {}).update(keys)
    return {section: keys for section, keys in out.items() if keys}


def write_profile(profile: dict, path: str, logs: list[str], cfg: Config | None = None) -> None:
    """The profile as TOML: with cfg (the tuned config), self-contained (`self_contained`), its
    header naming what tune fitted and what came from the config it started from; without, the
    profile's keys alone."""
    full = self_contained(profile, cfg) if cfg is not None else profile
    fitted = {k for keys in profile.values() for k in keys}
    kept = sorted(k for keys in full.values() for k in keys if k not in fitted)
    lines = ["# guard's noise model fitted by guard tune to these clean logs:"]
    lines += [f"#   {Path(log).name}" for log in logs]
    if kept:
        lines += ["# Beside what it fitted, the settings of the config it started from that differ from guard's",
                  f"# defaults: {', '.join(kept)}."]
    lines += ["# Use it with: guard run --config THIS_FILE (or guard replay ... --config THIS_FILE).", ""]
    try:
        Path(path).write_text("\n".join(lines) + "\n" + tomli_w.dumps(full))
    except OSError as e:
        raise GuardError(f"{path}: cannot write: {e.strerror}") from None
