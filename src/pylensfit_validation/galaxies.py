"""Round galaxy profiles and PSFs of the simulations, described once and built with GalSim.

The simulated sets (:mod:`pylensfit_validation.simulate`,
:mod:`pylensfit_validation.validation`, :mod:`pylensfit_validation.precision`,
:mod:`pylensfit_validation.convergence`) describe each galaxy by a
:class:`GalaxyProfile` and each PSF by a :class:`PSFProfile`, and build their GalSim
objects with :meth:`GalaxyProfile.galsim` and :meth:`PSFProfile.galsim`. The sets differ
only in their parameters:

* STEP1-like fields and the model bank's families (:meth:`GalaxyProfile.from_model`):
  ``r`` is the exponential's scale length, the de Vaucouleurs half-light radius, and the
  bulge+disc's disc scale length with a bulge of half-light radius ``0.6 r`` and half the
  flux (:class:`~pylensfit.Config`'s ``bulge_size_ratio`` and ``bulge_fraction``);
* STEP2-like and precision sets: every size a half-light radius, the bulge's half that
  of its disc, Sersic profiles and discs with star-forming knots.

All sizes are in pixels (the simulations draw with ``scale=1``). A galaxy profile is
of unit flux and, unless its bulge has a shape of its own (``bulge_shear``), round: the
callers shear, rotate, scale and convolve it. :func:`inner_shear` gives the bulge's own
shear that makes it end at a chosen ellipticity once the galaxy's intrinsic shape is
applied (a bulge misaligned with, or rounder than, its disc).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from pylensfit.models import DEVAUC_TRUNCATION

__all__ = [
    "GALAXY_KINDS",
    "PSF_KINDS",
    "REALISTIC",
    "GalaxyProfile",
    "PSFProfile",
    "draw_bulge_shapes",
    "draw_sersic_indices",
    "inner_shear",
]

#: Galaxy kinds of :class:`GalaxyProfile`.
GALAXY_KINDS: tuple[str, ...] = ("exponential", "devaucouleurs", "sersic", "bulge+disc", "knots")
#: PSF kinds of :class:`PSFProfile`.
PSF_KINDS: tuple[str, ...] = ("moffat", "kolmogorov", "asymmetric")

#: The ranges of the simulations' realistic populations (bulges as COSMOS fits have
#: them, which no model of the bulge+disc family holds): the Sersic index
#: (log-uniform), the bulge's half-light radius over its disc's (uniform), the bulge's
#: ellipticity over its disc's per kind (uniform), and the rms of the bulge's position
#: angle less its disc's per kind (degrees, Gaussian, clipped to +-90).
REALISTIC: dict[str, tuple[float, float]] = {
    "sersic_n": (0.3, 6.0),
    "bulge_size_ratio": (0.25, 0.8),
    "bulge+disc e_ratio": (0.2, 1.0),
    "knots e_ratio": (0.0, 0.6),
    "misalign_rms": (30.0, 10.0),  # bulge+disc, knots
}

#: Kinds whose size may be a scale length: those whose size is an exponential's.
_SCALE_KINDS = ("exponential", "bulge+disc")


@dataclass(frozen=True)
class GalaxyProfile:
    """One galaxy's round, unit-flux profile.

    Parameters
    ----------
    kind : {"exponential", "devaucouleurs", "sersic", "bulge+disc", "knots"}
        The profile: an exponential disc; a de Vaucouleurs profile; a Sersic profile of
        index ``sersic_n``; a de Vaucouleurs bulge plus an exponential disc; or a bulge, a
        disc and star-forming knots that follow the disc (``galsim.RandomKnots``).
    size : float
        Size in pixels: the half-light radius of the profile (of its disc for
        ``"bulge+disc"`` and ``"knots"``), or the exponential's (disc's) scale length
        with ``size_kind="scale"``.
    size_kind : {"half_light", "scale"}
        What ``size`` is. ``"scale"`` only for the kinds whose size is an exponential's,
        ``"exponential"`` and ``"bulge+disc"``.
    sersic_n : float
        Sersic index (``kind="sersic"`` only).
    bulge_fraction : float
        The bulge's fraction of the flux (``"bulge+disc"``, ``"knots"``); the disc, knots
        included, has the rest.
    bulge_size_ratio : float
        The bulge's half-light radius over ``size`` (whatever ``size_kind``): 0.6 for the
        model bank's bulge+disc (``size`` a scale length), 0.5 for the STEP2-like sets
        (``size`` a half-light radius).
    knot_fraction : float
        The knots' fraction of the disc's flux (``kind="knots"``).
    n_knots : int
        Number of knots (``kind="knots"``).
    knot_seed : int
        Seed of the knots' positions (``galsim.BaseDeviate(knot_seed)``): the same seed,
        the same knots.
    truncation : float
        Truncation radius of the de Vaucouleurs profiles (the bulge's too) and of the
        Sersic profiles of index above 2, in their half-light radii (the profile's
        half-light radius is that of the truncated profile, GalSim's default). Sersic
        profiles of index 2 or less are not truncated.
    bulge_shear : tuple of float
        ``(g1, g2)``, the reduced shear applied to the bulge alone (``"bulge+disc"``,
        ``"knots"``) before the galaxy's intrinsic shape is applied to the whole: ``(0,
        0)``, the default, gives a bulge aligned with its disc and as elongated;
        :func:`inner_shear` gives the one that ends the bulge at a chosen ellipticity.

    Raises
    ------
    ValueError
        For an unknown ``kind`` or ``size_kind``, ``size_kind="scale"`` with a kind
        whose size is no exponential's, or a ``size`` not above 0.
    """

    kind: str
    size: float
    size_kind: str = "half_light"
    sersic_n: float = 1.0
    bulge_fraction: float = 0.5
    bulge_size_ratio: float = 0.5
    knot_fraction: float = 0.0
    n_knots: int = 0
    knot_seed: int = 0
    truncation: float = DEVAUC_TRUNCATION
    bulge_shear: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        if self.kind not in GALAXY_KINDS:
            raise ValueError(f"unknown galaxy kind {self.kind!r}; one of {GALAXY_KINDS}")
        if self.size_kind not in ("half_light", "scale"):
            raise ValueError(f"size_kind must be 'half_light' or 'scale', not {self.size_kind!r}")
        if self.size_kind == "scale" and self.kind not in _SCALE_KINDS:
            raise ValueError(f"a {self.kind!r} galaxy's size is a half-light radius")
        if not self.size > 0:
            raise ValueError(f"size must be > 0 pixels, got {self.size}")
        if not np.hypot(*self.bulge_shear) < 1:
            raise ValueError(f"bulge_shear must have |g| < 1, got {self.bulge_shear}")

    @classmethod
    def from_model(
        cls, kind: str, r: float, *, bulge_fraction: float = 0.5, bulge_size_ratio: float = 0.6
    ) -> GalaxyProfile:
        """The profile of a model-bank family, ``r`` with the bank's meaning.

        Parameters
        ----------
        kind : {"exponential", "devaucouleurs", "bulge+disc"}
            The family (:data:`pylensfit.models.MODEL_TYPES`).
        r : float
            Size in pixels (:mod:`pylensfit.models`): the exponential's scale length,
            the de Vaucouleurs half-light radius, the bulge+disc's disc scale length.
        bulge_fraction : float
            The bulge+disc's bulge fraction of the flux (default ``Config``'s, 0.5).
        bulge_size_ratio : float
            The bulge's half-light radius over the disc's scale length (default
            ``Config``'s, 0.6).

        Returns
        -------
        GalaxyProfile
            The description.

        Raises
        ------
        ValueError
            For a kind that is no family of the model bank.
        """
        if kind not in ("exponential", "devaucouleurs", "bulge+disc"):
            raise ValueError(f"unknown model {kind!r}")
        return cls(kind, r, size_kind="half_light" if kind == "devaucouleurs" else "scale",
                   bulge_fraction=bulge_fraction, bulge_size_ratio=bulge_size_ratio)  # fmt: skip

    def galsim(self):
        """The GalSim profile.

        Returns
        -------
        galsim.GSObject
            Unit flux, centred on the origin (sizes in pixels), before any shear and
            PSF; round unless ``bulge_shear`` is not zero. ``"bulge+disc"`` is
            ``galsim.Add(bulge, disc)``, ``"knots"`` ``galsim.Add(bulge, disc, knots)``.
        """
        import galsim  # galsim: heavy import (seconds), only when a profile is rendered

        T = self.truncation
        r = self.size

        def exponential(radius):
            if self.size_kind == "scale":
                return galsim.Exponential(scale_radius=radius)
            return galsim.Exponential(half_light_radius=radius)

        if self.kind == "exponential":
            return exponential(r)
        if self.kind == "devaucouleurs":
            return galsim.DeVaucouleurs(half_light_radius=r, trunc=T * r)
        if self.kind == "sersic":
            n = self.sersic_n
            return galsim.Sersic(n=n, half_light_radius=r, trunc=T * r if n > 2 else 0.0)
        rb = self.bulge_size_ratio * r
        bulge = galsim.DeVaucouleurs(half_light_radius=rb, trunc=T * rb)
        bulge = bulge.withFlux(self.bulge_fraction)
        if self.bulge_shear[0] or self.bulge_shear[1]:
            bulge = bulge.shear(g1=float(self.bulge_shear[0]), g2=float(self.bulge_shear[1]))
        disc_flux = 1.0 - self.bulge_fraction
        if self.kind == "bulge+disc":
            return galsim.Add(bulge, exponential(r).withFlux(disc_flux))
        # "knots": a disc with star-forming knots that follow it
        knots = galsim.RandomKnots(self.n_knots, half_light_radius=r,
                                   flux=self.knot_fraction * disc_flux,
                                   rng=galsim.BaseDeviate(self.knot_seed))  # fmt: skip
        disc = exponential(r).withFlux((1 - self.knot_fraction) * disc_flux)
        return galsim.Add(bulge, disc, knots)


@dataclass(frozen=True)
class PSFProfile:
    """A PSF profile, without the pixel response.

    Parameters
    ----------
    kind : {"moffat", "kolmogorov", "asymmetric"}
        A Moffat profile of index ``beta``; a Kolmogorov profile; or a coma-like
        asymmetric PSF, a Moffat core with a fainter, broader Moffat lobe (FWHM
        ``lobe_size_ratio * fwhm``, flux ``lobe_flux``) displaced by ``lobe_shift``
        along x.
    fwhm : float
        FWHM in pixels (of the core for ``"asymmetric"``), before the shear.
    beta : float
        Moffat index (not used by ``"kolmogorov"``).
    e1, e2 : float
        Ellipticity, GalSim's reduced shear ``g`` applied to the whole profile (pixel
        frame).
    lobe_flux : float
        The lobe's fraction of the flux (``"asymmetric"``).
    lobe_shift : float
        The lobe's displacement along x in pixels, before the shear (``"asymmetric"``).
    lobe_size_ratio : float
        The lobe's FWHM over the core's (``"asymmetric"``).

    Raises
    ------
    ValueError
        For an unknown ``kind`` or a ``fwhm`` not above 0.
    """

    kind: str = "moffat"
    fwhm: float = 3.0
    beta: float = 3.5
    e1: float = 0.0
    e2: float = 0.0
    lobe_flux: float = 0.0
    lobe_shift: float = 0.0
    lobe_size_ratio: float = 1.5

    def __post_init__(self) -> None:
        if self.kind not in PSF_KINDS:
            raise ValueError(f"unknown PSF kind {self.kind!r}; one of {PSF_KINDS}")
        if not self.fwhm > 0:
            raise ValueError(f"fwhm must be > 0 pixels, got {self.fwhm}")

    @classmethod
    def from_dict(cls, p: Mapping) -> PSFProfile:
        """The PSF of a dictionary as the simulated sets write them.

        Parameters
        ----------
        p : mapping
            ``{"fwhm", "beta", "e1", "e2"}`` (a Moffat: STEP-like sets, a manifest's
            ``psfs`` entries), optionally ``"kind"`` (default ``"moffat"``; a
            ``"kolmogorov"`` needs no ``"beta"``) and ``"lobe_flux"``, ``"lobe_shift"``
            (``"asymmetric"``, :data:`pylensfit_validation.precision.PRECISION_PSFS`). Other keys
            (``"name"``) are ignored.

        Returns
        -------
        PSFProfile
            The description.

        Raises
        ------
        KeyError
            For a missing ``fwhm``, ``e1``, ``e2``, or ``beta`` of a Moffat kind.
        """
        kind = p.get("kind", "moffat")
        kw = {} if kind == "kolmogorov" else {"beta": p["beta"]}
        if kind == "asymmetric":
            kw.update(lobe_flux=p["lobe_flux"], lobe_shift=p["lobe_shift"])
        return cls(kind, p["fwhm"], e1=p["e1"], e2=p["e2"], **kw)

    def galsim(self):
        """The GalSim profile.

        Returns
        -------
        galsim.GSObject
            Unit flux, in pixels, without the pixel response (draw it with GalSim's,
            ``scale=1``).
        """
        import galsim  # galsim: heavy import (seconds), only when a profile is rendered

        if self.kind == "moffat":
            psf = galsim.Moffat(beta=self.beta, fwhm=self.fwhm)
        elif self.kind == "kolmogorov":
            psf = galsim.Kolmogorov(fwhm=self.fwhm)
        else:  # "asymmetric"
            core = galsim.Moffat(beta=self.beta, fwhm=self.fwhm).withFlux(1.0 - self.lobe_flux)
            lobe = galsim.Moffat(beta=self.beta, fwhm=self.lobe_size_ratio * self.fwhm)
            lobe = lobe.withFlux(self.lobe_flux)
            psf = galsim.Add(core, lobe.shift(self.lobe_shift, 0.0))
        return psf.shear(g1=self.e1, g2=self.e2)


def _shear_matrix(g1: np.ndarray, g2: np.ndarray) -> np.ndarray:
    """GalSim's shear matrices ``[[1 + g1, g2], [g2, 1 - g1]] / sqrt(1 - |g|^2)``, ``(n, 2, 2)``."""
    norm = 1.0 / np.sqrt(1.0 - g1 * g1 - g2 * g2)
    return np.stack([np.stack([1 + g1, g2], -1), np.stack([g2, 1 - g1], -1)], -2) * norm[
        ..., None, None
    ]


def inner_shear(outer, target) -> tuple[np.ndarray, np.ndarray]:
    """The shear ``b`` that, followed by ``outer``, takes a round profile to ``target``.

    A component of a galaxy (its bulge) sheared first by ``b`` and then, with the rest of
    the galaxy, by the galaxy's intrinsic shape ``outer`` ends with the ellipticity
    ``target``: its second moments are those of ``S(outer) S(b)``, where ``S(g)`` is
    GalSim's shear matrix, and ``b`` is the one for which ``S(b)^2 = S(outer)^-1
    S(target)^2 S(outer)^-1``. Shears do not commute, so ``b`` is not ``target -
    outer``.

    Parameters
    ----------
    outer : array_like
        ``(..., 2)`` reduced shears ``(g1, g2)`` applied second (the galaxy's
        intrinsic shape), ``|g| < 1``.
    target : array_like
        ``(..., 2)`` the component's wanted reduced-shear ellipticities, ``|g| < 1``.

    Returns
    -------
    tuple of numpy.ndarray
        ``(b1, b2)``, the inner reduced shears, of the broadcast shape of the inputs less
        their last axis.
    """
    o = np.asarray(outer, float)
    t = np.asarray(target, float)
    so_inv = _shear_matrix(-o[..., 0], -o[..., 1])
    st = _shear_matrix(t[..., 0], t[..., 1])
    q = so_inv @ st @ st @ so_inv
    tr = q[..., 0, 0] + q[..., 1, 1]
    d1 = (q[..., 0, 0] - q[..., 1, 1]) / tr
    d2 = 2.0 * q[..., 0, 1] / tr
    f = 1.0 / (1.0 + np.sqrt(np.maximum(1.0 - d1 * d1 - d2 * d2, 0.0)))  # distortion to g
    return d1 * f, d2 * f


def draw_sersic_indices(n: int, rng) -> np.ndarray:
    """``n`` Sersic indices log-uniform over :data:`REALISTIC` ``"sersic_n"``, rounded to
    0.1 (GalSim caches its Sersic profiles by index)."""
    lo, hi = np.log(REALISTIC["sersic_n"])
    return np.round(np.exp(rng.uniform(lo, hi, n)), 1)


def draw_bulge_shapes(bulge_disc, knotty, e_int, rng) -> tuple[np.ndarray, ...]:
    """Bulges of their own size and shape, as :data:`REALISTIC` draws them.

    Parameters
    ----------
    bulge_disc, knotty : array_like of bool
        ``(n,)`` which galaxies are bulge+disc and which knotty discs (the others get
        ``bulge_shear = (0, 0)``).
    e_int : array_like
        ``(n, 2)`` the discs' intrinsic reduced-shear ellipticities (the galaxy's shape,
        applied to the whole after the bulge's own).
    rng : numpy.random.Generator
        The draws, five arrays of ``n`` in a fixed order whatever the kinds.

    Returns
    -------
    size_ratio : numpy.ndarray
        The bulge's half-light radius over its disc's.
    b1, b2 : numpy.ndarray
        The bulge's own shear (:class:`GalaxyProfile`'s ``bulge_shear``), from
        :func:`inner_shear`: with the disc's shape after it, the bulge ends ``e_ratio``
        times as elongated as its disc and misaligned by ``misalign``.
    misalign : numpy.ndarray
        The bulge's position angle less its disc's, degrees (0 where no bulge).
    """
    bd = np.asarray(bulge_disc, bool)
    kn = np.asarray(knotty, bool)
    e = np.asarray(e_int, float)
    n = bd.size
    size_ratio = rng.uniform(*REALISTIC["bulge_size_ratio"], n)
    ratio = np.where(kn, rng.uniform(*REALISTIC["knots e_ratio"], n),
                     rng.uniform(*REALISTIC["bulge+disc e_ratio"], n))  # fmt: skip
    rms = np.where(kn, REALISTIC["misalign_rms"][1], REALISTIC["misalign_rms"][0])
    dphi = np.clip(rng.normal(0.0, 1.0, n) * rms, -90.0, 90.0)
    ed = e[:, 0] + 1j * e[:, 1]
    eb = ratio * ed * np.exp(2j * np.deg2rad(dphi))
    b1, b2 = inner_shear(e, np.stack([eb.real, eb.imag], -1))
    has = bd | kn
    return size_ratio, np.where(has, b1, 0.0), np.where(has, b2, 0.0), np.where(has, dphi, 0.0)
