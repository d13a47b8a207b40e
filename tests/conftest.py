"""Shared helpers: GalSim renderings with the pylensfit centring convention; the
suite's model banks kept in a temporary folder, not the user's cache."""

import os
import tempfile
from pathlib import Path

import galsim
import numpy as np
import pytest

# every worker of the suite shares one folder of model banks (pylensfit._util.disk_cached)
os.environ.setdefault("PYLENSFIT_CACHE_DIR",
                      str(Path(tempfile.gettempdir()) / f"pylensfit-tests-{os.getuid()}"))

#: the package's in-memory caches of banks (module, name): emptied after each test file,
#: so that a worker running many files holds the banks of one file at a time
_CACHES = (("pylensfit.joint", "_SUBSETS"), ("pylensfit.joint", "_BANKS"),
           ("pylensfit.likelihood.bank", "_PSF_BANKS"),
           ("pylensfit.likelihood.folded", "_FOLDED"), ("pylensfit.likelihood.folded", "_ACTIVE"),
           ("pylensfit.likelihood.pairs", "_PAIR_BANKS"), ("pylensfit.likelihood.pairs", "_G2HAT"),
           ("pylensfit.likelihood.device", "_ON_DEVICE"))


@pytest.fixture(autouse=True, scope="module")
def _release_bank_caches():
    yield
    import gc  # only at a test file's end
    import sys

    for mod, name in _CACHES:
        m = sys.modules.get(mod)
        if m is not None:
            getattr(m, name).clear()
    models = sys.modules.get("pylensfit.models")
    if models is not None:
        for f in vars(models).values():
            if hasattr(f, "cache_clear"):
                f.cache_clear()
    gc.collect()

N = 32


def draw(obj, n=N, offset=(0.0, 0.0), flux=1.0):
    """Draw ``obj`` (with the pixel response) on ``n x n`` centred on element [n//2, n//2].

    GalSim centres an even-sized image on the half-integer ``true_center``; an extra
    half-pixel offset puts the profile centre on the integer element [n//2, n//2].
    """
    half = 0.5 if n % 2 == 0 else 0.0
    return obj.withFlux(flux).drawImage(
        nx=n, ny=n, scale=1.0, offset=(offset[0] + half, offset[1] + half)
    ).array


def galsim_model(model, r, e1=0.0, e2=0.0, bulge_fraction=0.5, bulge_size_ratio=0.6):
    """The pylensfit model of size ``r`` (pixels) and ellipticity ``e`` as a GalSim object."""
    from pylensfit.models import DEVAUC_TRUNCATION as T

    if model == "exponential":
        prof = galsim.Exponential(scale_radius=r)
    elif model == "devaucouleurs":
        prof = galsim.DeVaucouleurs(half_light_radius=r, trunc=T * r)
    else:
        rb = bulge_size_ratio * r
        prof = galsim.Add(
            galsim.DeVaucouleurs(half_light_radius=rb, trunc=T * rb).withFlux(bulge_fraction),
            galsim.Exponential(scale_radius=r).withFlux(1.0 - bulge_fraction),
        )
    return prof.shear(g1=e1, g2=e2)


PSFS = {
    "moffat_round": galsim.Moffat(beta=3.5, fwhm=3.0),
    "moffat_e1": galsim.Moffat(beta=3.5, fwhm=3.2).shear(g1=0.08, g2=0.0),
    "kolmogorov_e2": galsim.Kolmogorov(fwhm=3.5).shear(g1=-0.03, g2=0.07),
}


@pytest.fixture(scope="session")
def psfs():
    return PSFS


@pytest.fixture
def rng():
    return np.random.default_rng(20081208)


def check_catalogue_invariants(cat) -> None:
    """A row's flags, fitclass, weight and shape agree: ``flags == 0`` means a measured
    object (fitclass 0 or 1) with a finite shape if a galaxy; only such galaxies have
    weight > 0; an object not measured (fitclass -1) says why in its flags."""
    flags = np.asarray(cat["flags"])
    fitclass = np.asarray(cat["fitclass"])
    weight = np.asarray(cat["weight"], dtype=float)
    e1, e2 = (np.asarray(cat[c], dtype=float) for c in ("e1", "e2"))
    clean = flags == 0
    assert np.isin(fitclass[clean], (0, 1)).all(), "flags 0 but not measured"
    galaxy = clean & (fitclass == 0)
    assert (np.isfinite(e1[galaxy]) & np.isfinite(e2[galaxy])).all(), "flags 0, no shape"
    assert np.isfinite(weight).all() and (weight >= 0).all()
    assert not ((weight > 0) & ~galaxy).any(), "weight > 0 for a flagged row or a star"
    assert (flags[fitclass == -1] != 0).all(), "not measured, yet no flag"


@pytest.fixture(autouse=True)
def _every_written_catalogue_is_consistent(monkeypatch):
    """Every catalogue that ``measure`` writes in any test holds the invariants of
    :func:`check_catalogue_invariants` (tables that tests build by hand are theirs)."""
    from pylensfit.images import run  # measure looks write_catalogue up there

    write = run.write_catalogue

    def checked(cat, path, **kw):
        if {"flags", "fitclass", "weight", "e1", "e2"} <= set(cat.colnames):
            check_catalogue_invariants(cat)
        return write(cat, path, **kw)

    monkeypatch.setattr(run, "write_catalogue", checked)
