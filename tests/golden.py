"""The golden catalogues' inputs and columns: fixed-seed fields for ``measure`` and
fixed-seed stamps for ``measure_stamps``, rendered with GalSim directly (not with the
package's own simulations), so that a change of the package's layout that changes no
method gives the same numbers.

``python tests/golden.py`` writes ``tests/data/golden.npz`` from the package as it is;
``tests/test_golden.py`` compares the package with it.
"""

from __future__ import annotations

from pathlib import Path

import galsim
import numpy as np
from astropy.io import fits

import pylensfit as plf

DATA = Path(__file__).parent / "data" / "golden.npz"
#: the columns compared, catalogue and stamps alike
COLUMNS = ("e1", "e2", "e1_var", "e2_var", "e12_cov", "sens1", "sens2", "weight", "flags")
N_FIELD = 256  # field side (pixels)
PSF = galsim.Moffat(beta=3.5, fwhm=3.0).shear(g1=0.03, g2=-0.02)  # pixels


def _field(seed: int, stars: bool = False) -> np.ndarray:
    """A ``N_FIELD`` field of exponential and de Vaucouleurs galaxies (or stars) on a
    jittered lattice, sheared by (0.03, -0.01), with unit white noise."""
    rng = np.random.default_rng(seed)
    img = galsim.ImageF(N_FIELD, N_FIELD, scale=1.0)
    pos = np.arange(20, N_FIELD - 19, 26, dtype=float)
    for k, (x, y) in enumerate((a, b) for a in pos for b in pos):
        x, y = x + rng.uniform(-3, 3), y + rng.uniform(-3, 3)
        if stars:
            obj = galsim.DeltaFunction(flux=rng.uniform(500, 5000))
        else:
            e = rng.uniform(0, 0.5) * np.exp(2j * rng.uniform(0, np.pi))
            prof = (galsim.Exponential(half_light_radius=rng.uniform(1.5, 3.5)) if k % 2 else
                    galsim.DeVaucouleurs(half_light_radius=rng.uniform(1.5, 3.0), trunc=20))
            obj = prof.withFlux(rng.uniform(150, 1200)).shear(g1=e.real, g2=e.imag)
            obj = obj.shear(g1=0.03, g2=-0.01)
        stamp = galsim.Convolve(obj, PSF).drawImage(nx=48, ny=48, scale=1.0,
                                                    center=galsim.PositionD(x + 1, y + 1))
        b = stamp.bounds & img.bounds
        img[b] += stamp[b]
    img.addNoise(galsim.GaussianNoise(galsim.BaseDeviate(seed + 100), sigma=1.0))
    return img.array


def write_fields(folder: Path) -> tuple[list[Path], Path]:
    """The two galaxy fields and the star field, as FITS files in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, seed, stars in (("a", 1, False), ("b", 2, False), ("stars", 3, True)):
        p = folder / f"{name}.fits"
        fits.PrimaryHDU(_field(seed, stars).astype(np.float32)).writeto(p, overwrite=True)
        paths.append(p)
    return paths[:2], paths[2]


def stamps(n: int = 120, seed: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """``n`` 32-pixel stamps of sheared exponentials (S/N 15-100) and the PSF image."""
    rng = np.random.default_rng(seed)
    out = np.empty((n, 32, 32), np.float32)
    for i in range(n):
        e = rng.uniform(0, 0.5) * np.exp(2j * rng.uniform(0, np.pi))
        gal = galsim.Exponential(half_light_radius=rng.uniform(1.2, 3.0))
        gal = gal.withFlux(rng.uniform(150, 1000)).shear(g1=e.real, g2=e.imag)
        gal = gal.shear(g1=0.02, g2=0.01)
        off = rng.uniform(-0.5, 0.5, 2)
        out[i] = galsim.Convolve(gal, PSF).drawImage(nx=32, ny=32, scale=1.0,
                                                     offset=(off[0] + 0.5, off[1] + 0.5)).array
    out += rng.normal(0.0, 1.0, out.shape).astype(np.float32)
    psf = PSF.drawImage(nx=32, ny=32, scale=1.0, offset=(0.5, 0.5)).array
    return out, psf


def measured(folder: Path) -> dict[str, np.ndarray]:
    """The golden columns of ``measure`` (default configuration) on the two fields and
    of ``measure_stamps`` on the stamps, keyed ``cat_<column>`` and ``stamps_<column>``."""
    fields, star = write_fields(folder)
    cat = plf.measure(fields, stars=[star], progress=False)
    st, psf = stamps()
    tab = plf.measure_stamps(st, psf, noise_sigma=1.0)
    out = {f"cat_{c}": np.asarray(cat[c]) for c in COLUMNS + ("x", "y")}
    out.update({f"stamps_{c}": np.asarray(tab[c]) for c in COLUMNS})
    return out


if __name__ == "__main__":
    import tempfile
    import warnings

    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        np.savez_compressed(DATA, **measured(Path(tmp)))
    print(f"{DATA}: written")
