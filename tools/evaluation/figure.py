"""One run of one case, kept: its tlog and truth, its report and its three-panel figure."""

from __future__ import annotations

import sys
from pathlib import Path

from guard_sim.run import run
from tools.evaluation.cases import ALL_FAMILIES, base_scenario, cases, detector_config, phased, sim_seed, vehicle


def figure(case: str, seed: int, out: Path, settings: tuple[str, ...] = (), detector: str = "cusum",
           vehicles: bool = False) -> int:
    """One run of one case: its tlog and truth, the replay report (`detector`, with `settings`) and
    the three-panel figure; with `vehicles`, on the second family's vehicle of that seed, as the
    campaign ran it."""
    from guard.sinks.plot import plot
    from guard.runtime.replay import replay, write_report
    from guard.sinks.plot import Trace
    found = [c for c in cases(list(ALL_FAMILIES)) if c[1] == case]
    if not found:
        print(f"eval: no case {case!r}; the cases are: " + "; ".join(c[1] for c in cases(list(ALL_FAMILIES))),
              file=sys.stderr)
        return 2
    family, name, attacks, duration = found[0]
    attacks, duration = phased(family, attacks, duration, seed)
    out.mkdir(parents=True, exist_ok=True)
    stem = out / f"{name.replace(' ', '_').replace('/', '_')}-seed{seed}"
    sc = base_scenario(family, duration, attacks, vehicle(seed) if vehicles else None)
    truth = run(sc, sim_seed(family, attacks, seed), tlog=f"{stem}.tlog")
    trace = Trace()
    report = replay(f"{stem}.tlog", detector_config(detector, settings), listeners=(trace,))
    write_report(report, f"{stem}.json")
    plot(trace, report, f"{stem}.png", truth)
    first = report["alarms"][0] if report["alarms"] else None
    print(f"{stem}.tlog, .json, .png: " + (f"first alarm at GNSS sample {first['gnss_index']} "
          f"({'|'.join([first['sensor'], *first['ambiguous_with']])} {first['channel']})" if first else "no alarm"))
    return 0
