"""The quick tier: small STEP1- and STEP2-like sets simulated and validated in minutes."""

from __future__ import annotations

import time
from pathlib import Path

from astropy.table import Table

from pylensfit.config import Config

from .step import read_manifest, simulate_step
from .validate import validate

__all__ = [
    "QUICK_NGAL",
    "QUICK_PRIOR_NGAL",
    "quick_validation",
]


# ----------------------------------------------------------------------------------------
# The quick tier
# ----------------------------------------------------------------------------------------
#: Galaxies over the shear fields of the quick tier (set by timing on 2 cores, jobs=2).
QUICK_NGAL: dict[str, int] = {"step1": 5000, "step2": 5000}
#: Galaxies over the zero-shear (prior) fields of the quick tier.
QUICK_PRIOR_NGAL: dict[str, int] = {"step1": 2500, "step2": 2500}


def quick_validation(
    out: str | Path,
    *,
    jobs: int = 1,
    seed: int = 1,
    progress: bool = True,
    ngal: dict[str, int] | None = None,
    config=None,
    estimator: str = "fixed-point",
) -> dict[str, Table]:
    """The quick tier of the validation: small STEP1 and STEP2 sets, simulated and validated.

    Simulates ``out/step1`` and ``out/step2`` (:func:`simulate_step`, ``ngal`` galaxies
    over the shear fields, default :data:`QUICK_NGAL`, and :data:`QUICK_PRIOR_NGAL` over
    the zero-shear fields from which the prior is estimated; an existing set with the same
    parameters is reused), validates both (:func:`validate`, reports
    ``out/step1/report.md`` and ``out/step2/report.md``) and writes ``out/README.md``
    linking them with the timings. With ``jobs=2`` on two cores the whole tier takes
    under 10 minutes (see the package's documentation for the measured time). The sets
    are too small to test ``|<m>| <= 0.006`` (sigma(m) is several 0.01); the tier checks
    that the whole chain runs and shows no gross bias, and the reports say which targets
    the set can test.

    Parameters
    ----------
    out : str or pathlib.Path
        Output directory.
    jobs : int
        Worker processes for measuring.
    seed : int
        Master seed of the simulations (step2 uses ``seed + 1``).
    progress : bool
        Progress bars and one line per stage.
    ngal : dict, optional
        ``{"step1": n, "step2": n}`` overriding :data:`QUICK_NGAL`.
    config : Config, optional
        Pipeline settings (default ``Config()``, :func:`validate`'s).
    estimator : {"fixed-point", "key2"}
        Shear estimator (as :func:`validate`).

    Returns
    -------
    dict
        ``{"step1": table, "step2": table}`` from :func:`validate`, each with
        ``meta["timing"]`` (seconds: ``simulate``, ``validate``).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    n = {**QUICK_NGAL, **(ngal or {})}
    results: dict[str, Table] = {}
    for i, kind in enumerate(("step1", "step2")):
        d = out / kind
        t0 = time.perf_counter()
        want = {"kind": kind, "ngal": int(n[kind]), "seed": int(seed + i),
                "prior_ngal": int(QUICK_PRIOR_NGAL[kind])}  # fmt: skip
        try:
            have = read_manifest(d)
            reuse = all(have.get(k) == v for k, v in want.items())
        except (OSError, ValueError):
            reuse = False
        if not reuse:
            if progress:
                print(f"quick tier: simulating {kind} ({n[kind]} galaxies) in {d}", flush=True)
            simulate_step(kind, d, ngal=int(n[kind]), seed=int(seed + i),
                          prior_ngal=QUICK_PRIOR_NGAL[kind], jobs=jobs,
                          progress=progress)  # fmt: skip
        t1 = time.perf_counter()
        if progress:
            print(f"quick tier: validating {kind}", flush=True)
        res = validate(d, config=config or Config(), jobs=jobs, estimator=estimator,
                       report=d / "report.md", progress=progress)  # fmt: skip
        t2 = time.perf_counter()
        res.meta["timing"] = {"simulate": t1 - t0, "validate": t2 - t1}
        results[kind] = res
    lines = ["# pylensfit quick validation", ""]
    for kind, res in results.items():
        m = res.meta
        tm = m["timing"]
        lines += [f"## {kind}: [report]({kind}/report.md)", "",
                  f"<m> = {m['mean_m']:+.4f} +- {m['mean_m_err']:.4f}, sigma_c = "
                  f"{m['sigma_c']:.2e}, Q = {res['Q'][-1]:.0f}, {res['n_gal'][-1]} galaxies "
                  f"({m['mode']}); simulate {tm['simulate']:.0f} s, validate "
                  f"{tm['validate']:.0f} s.", ""]  # fmt: skip
        for k, v in m["diagnosis"].items():
            if k in ("m", "sigma_c", "Q"):
                lines.append(f"- {k}: {v[0]} ({v[1]})")
        lines.append("")
    (out / "README.md").write_text("\n".join(lines))
    return results
