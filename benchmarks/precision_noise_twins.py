"""What noise twins buy in the precision mode: m's and c's errors with and without them.

`pylensfit validate --precision --noise-twins` renders every galaxy eight times: the
four renderings of the paired design (+g and -g, each with a 90-degree twin, the same
noise at +g and -g) and the same four with their noise fields negated. The noise's
first-order effect on each galaxy's posterior mean cancels between a rendering and its
noise twin; in c, which the +-g pairing leaves with the noise of every rendering, that is
most of the error. The run reports the same galaxies without their twins (breakdown
``no noise twins``, renderings 0-3 alone), so one run gives both. At the same number of
renderings the set without twins would have twice the galaxies and errors smaller by
sqrt(2); the twins' gain at equal cost is the ratio of the errors divided by that.

::

    python benchmarks/precision_noise_twins.py --ngal 16000 --ncal 20000 --jobs 2

(about 12 minutes on 2 cores.)
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from pylensfit_validation.precision import precision, spec_with


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--ngal", type=int, default=16000, help="galaxies (x8 renderings)")
    p.add_argument("--ncal", type=int, default=20000, help="calibration galaxies")
    p.add_argument("--seed", type=int, default=31)
    p.add_argument("--psf", nargs="+", help="PSFs by name (default all four)")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--report", help="write the precision report here")
    a = p.parse_args()
    spec = spec_with(ngal=a.ngal, ncal=a.ncal, seed=a.seed, psfs=a.psf, noise_twins=True)
    t0 = time.time()
    res = precision(spec, jobs=a.jobs, progress=False, report=a.report)
    print(f"{a.ngal} galaxies x 8 renderings in {time.time() - t0:.0f} s")
    res = res[res["estimator"] == "fixed-point"]
    cols = ["group", "m1", "m1_err", "m2", "m2_err", "c1", "c1_err", "c2", "c2_err", "n_gal"]
    twins = res[np.isin(res["breakdown"], ["all", "psf"])]
    plain = res[res["breakdown"] == "no noise twins"]
    ratios = []
    for name, t in (("with noise twins (8 renderings)", twins),
                    ("without (renderings 0-3 of the same galaxies)", plain)):  # fmt: skip
        t = t[cols]
        for c in cols[1:-1]:
            t[c].format = "+.5f"
        print(f"\n{name}:")
        t.pprint_all()
    for g in plain["group"]:
        a_, b_ = twins[twins["group"] == g][0], plain[plain["group"] == g][0]
        ratios.append([b_[f"{q}_err"] / a_[f"{q}_err"] / np.sqrt(2)
                       for q in ("m1", "m2", "c1", "c2")])  # fmt: skip
        d = [a_[q] - b_[q] for q in ("m1", "m2", "c1", "c2")]
        print(f"{g:>14}: with - without: m1 {d[0]:+.5f} m2 {d[1]:+.5f} "
              f"c1 {d[2]:+.6f} c2 {d[3]:+.6f}")
    r = np.array(ratios)
    print("\nerror without / with at the same number of renderings (m1, m2, c1, c2):")
    for g, row in zip(plain["group"], r, strict=True):
        print(f"{g:>14}: " + "  ".join(f"{v:.2f}" for v in row))
    print(f"mean: m {np.mean(r[:, :2]):.2f}, c {np.mean(r[:, 2:]):.2f}")


if __name__ == "__main__":
    main()
