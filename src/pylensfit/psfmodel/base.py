"""The interface of a PSF over the field (:class:`PSFModel`) and its simplest case,
one image everywhere (:class:`ConstantPSF`)."""

from __future__ import annotations

import hashlib
from abc import ABC, abstractmethod
from pathlib import Path

import numpy as np

from .._util import atomic_write_with
from ..psf import PSFResult
from .basis import CHUNK, moments_many, positions


def sha1(*parts) -> str:
    h = hashlib.sha1()
    for part in parts:
        if isinstance(part, np.ndarray):
            h.update(np.ascontiguousarray(part, dtype=np.float64).tobytes())
        elif isinstance(part, bytes):
            h.update(part)
        else:
            h.update(repr(part).encode())
        h.update(b"|")
    return h.hexdigest()


def atomic_write_bytes(data: bytes, path: Path, overwrite: bool) -> None:
    """Write ``data`` through a temporary file renamed when complete."""
    atomic_write_with(lambda tmp: Path(tmp).write_bytes(data), path, overwrite=overwrite)


# ---------------------------------------------------------------------------------------
# The interface
# ---------------------------------------------------------------------------------------
class PSFModel(ABC):
    """A PSF that may vary across the field.

    Attributes
    ----------
    size : int
        Side in pixels of the drawn images.
    diagnostics : dict
        How the model was made (stars used and rejected, polynomial order, held-out
        residuals; see the subclasses).
    """

    size: int
    diagnostics: dict

    @abstractmethod
    def _draw(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """``(n, size, size)`` images at 1-D positions."""

    def draw(self, x, y) -> np.ndarray:
        """The PSF at image positions.

        Parameters
        ----------
        x, y : float or array_like
            Scalars or 1-D arrays of 0-based image pixel positions (pixel centres on
            integers, ``x`` along the columns).

        Returns
        -------
        numpy.ndarray
            ``(size, size)`` for scalars, else ``(n, size, size)``; each image includes
            the pixel response, has unit sum and is centred on ``[size//2, size//2]``
            (the peak of its cross-correlation with a round Gaussian).
        """
        xa, ya, scalar = positions(x, y)
        out = self._draw(xa, ya)
        return out[0] if scalar else out

    def shape_at(self, x, y) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Adaptive-moment shape of the PSF at image positions.

        Parameters
        ----------
        x, y : float or array_like
            0-based image pixel positions, as for :meth:`draw`.

        Returns
        -------
        e1, e2, sigma : numpy.ndarray
            GalSim's adaptive-moment ellipticity ``(a - b) / (a + b)`` (``e1 > 0`` along
            x) and size ``det(M)^(1/4)`` in pixels of :meth:`draw` at each position
            (NaN where the moments fail); arrays of the positions' length (length 1 for
            scalars).
        """
        xa, ya, _ = positions(x, y)
        res = [moments_many(self._draw(xa[i : i + CHUNK], ya[i : i + CHUNK]))
               for i in range(0, xa.size, CHUNK)]  # fmt: skip
        sigma, e1, e2 = (np.concatenate([r[k] for r in res]) if res else np.zeros(0)
                         for k in range(3))  # fmt: skip
        return e1, e2, sigma

    @property
    @abstractmethod
    def centre(self) -> PSFResult:
        """The PSF at the field centre (or the constant PSF) as a :class:`PSFResult`."""

    @property
    @abstractmethod
    def digest(self) -> str:
        """SHA-1 hex digest of what defines the drawn images (for resume keys)."""

    @abstractmethod
    def write(self, path: str | Path, overwrite: bool = False) -> None:
        """Write the model to ``path`` atomically; :func:`read_psf_model` reads it back."""


# ---------------------------------------------------------------------------------------
# Constant
# ---------------------------------------------------------------------------------------
class ConstantPSF(PSFModel):
    """The same PSF image at every position.

    Parameters
    ----------
    psf : PSFResult
        The PSF (e.g. from :func:`pylensfit.psf.stack_psf` or
        :func:`pylensfit.psf.psf_from_image`), centred by the convention.
    """

    def __init__(self, psf: PSFResult):
        self.psf = psf
        self.size = psf.size
        image = np.asarray(psf.image, dtype=float)
        total = float(np.sum(image))
        # a unit-sum image (every PSFResult) is drawn as it is: dividing by a sum that
        # differs from 1 in the last bit would change every pixel by an ulp
        self._image = image if abs(total - 1.0) <= 1e-12 else image / total
        self.diagnostics = {"kind": "constant", "order": 0, "n_stars": int(psf.used.size),
                            "n_used": psf.n_used, "n_rejected": psf.n_rejected,
                            "source": psf.source}  # fmt: skip

    def __repr__(self) -> str:
        p = self.psf
        return f"ConstantPSF(size={self.size}, n_used={p.n_used}, source={p.source!r})"

    def _draw(self, x, y):
        return np.repeat(self._image[None], x.size, axis=0)

    @property
    def centre(self) -> PSFResult:
        return self.psf

    @property
    def digest(self) -> str:
        """The digest of the :class:`PSFResult` (the same resume key as the image alone)."""
        return self.psf.digest

    def write(self, path, overwrite=False):
        """Write as :meth:`PSFResult.write` does."""
        self.psf.write(path, overwrite=overwrite)
