"""The base of the ellipticity priors that depend on ``|e|`` only.

A form (:class:`~pylensfit.prior.functional.Prior`,
:class:`~pylensfit.prior.spline.SplinePrior`) supplies the unnormalised ``ln f(|e|)``
and its radial derivative; :class:`RadialPrior` normalises it on the ellipticity grid
(``sum_grid P(e) de^2 = 1``, so that ``P`` is a density in the (e1, e2) plane, per unit
e1 per unit e2), evaluates it, draws from it and writes it to JSON and FITS cards.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from .._util import check_egrid, json_kind, jsonable, other_file_hint, read_json
from ..grid import ellipticity_grid, grid_step

#: The forms, by name: each subclass of :class:`RadialPrior` with a ``form`` adds itself.
_FORMS: dict[str, type[RadialPrior]] = {}
#: The form of a prior dict that names none.
_DEFAULT_FORM = "functional"


class RadialPrior:
    """An ellipticity prior that depends on ``|e|`` only, normalised on a grid.

    The base of the two forms, the functional :class:`Prior` of Kitching et al. (2008)
    and the flexible :class:`SplinePrior`. A form supplies the unnormalised
    ``ln f(|e|)`` and its radial derivative; the density is ``P(e) = A f(|e|)`` with
    ``A`` fixed by ``sum_grid P de^2 = 1`` on :attr:`egrid` (units: per unit e1 per unit
    e2).

    Attributes
    ----------
    egrid : numpy.ndarray
        ``(n_e, 2)`` normalisation grid (cell centres).
    step : float
        Its cell side ``de``.
    A : float
        Normalisation constant, ``1 / sum_grid f(e) de^2`` (per unit e^2).
    method : str
        How the prior was obtained (``"fixed"`` when given).
    history : list of dict
        One entry per estimation step, with ``marginal_lnL`` where computed.
    info : dict
        Bookkeeping of the estimation: ``n_used``, ``n_excluded``, ``at_bound``, ...
    """

    #: the form's name in :meth:`to_dict` and in catalogue headers
    form = ""

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if cls.form:
            _FORMS[cls.form] = cls

    def _log_f(self, r: np.ndarray) -> np.ndarray:
        """Unnormalised ``ln P`` at radii ``0 <= r < 1``."""
        raise NotImplementedError

    def _dlogf_dr(self, r: np.ndarray) -> np.ndarray:
        """``d ln P / d|e|`` at radii ``0 < r < 1``."""
        raise NotImplementedError

    def _normalise(self, step: float | None, egrid: np.ndarray | None, method: str,
                   history, info) -> None:  # fmt: skip
        """Set the grid, its step and ``A``, and the bookkeeping."""
        if egrid is None:
            egrid = ellipticity_grid(0.1 if step is None else float(step))
        egrid = np.ascontiguousarray(egrid, dtype=float)
        self.step = float(f"{grid_step(egrid):.12g}")
        if step is not None and not math.isclose(float(step), self.step, rel_tol=1e-6):
            raise ValueError(f"step={step} disagrees with the grid's cell side {self.step}")
        r = np.hypot(egrid[:, 0], egrid[:, 1])
        if np.any(r >= 1.0):
            raise ValueError("the normalisation grid must lie inside |e| < 1")
        self.egrid = egrid
        self.method = method
        self.history: list[dict[str, Any]] = [dict(h) for h in (history or [])]
        self.info: dict[str, Any] = dict(info or {})
        lf = self._log_f(r)
        m = float(np.max(lf))
        self._log_norm = m + math.log(float(np.sum(np.exp(lf - m))) * self.step**2)
        self.A = math.exp(-self._log_norm)

    # -- evaluation ------------------------------------------------------------------
    def log_pdf(self, e1: np.ndarray | float, e2: np.ndarray | float) -> np.ndarray:
        """Natural log of :meth:`pdf` (``-inf`` for ``|e| >= 1``)."""
        e1, e2 = np.broadcast_arrays(np.asarray(e1, dtype=float), np.asarray(e2, dtype=float))
        r = np.hypot(e1, e2)
        inside = r < 1.0
        out = np.full(r.shape, -np.inf)
        out[inside] = self._log_f(r[inside]) - self._log_norm
        return out

    def pdf(self, e1: np.ndarray | float, e2: np.ndarray | float) -> np.ndarray:
        """Prior density at ``(e1, e2)``.

        Parameters
        ----------
        e1, e2 : array_like
            Ellipticity components (broadcast together).

        Returns
        -------
        numpy.ndarray
            ``P(e)`` per unit e^2, with ``A`` fixed by ``sum_grid P de^2 = 1`` on
            :attr:`egrid`; zero for ``|e| >= 1``.
        """
        return np.exp(self.log_pdf(e1, e2))

    def grad(self, e1: np.ndarray | float, e2: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Analytic gradient ``(dP/de1, dP/de2)`` of :meth:`pdf` (same normalisation).

        ``P`` depends on ``|e|`` only, so ``dP/de_i = P (d ln P / d|e|) e_i / |e|``. At
        ``e = 0`` the prior may have a cusp and the gradient need not exist; there (and
        for ``|e| >= 1``) zeros are returned. The grids of
        :func:`pylensfit.ellipticity_grid` never contain ``e = 0``.

        Returns
        -------
        tuple of numpy.ndarray
            ``dP/de1, dP/de2`` per unit e^3.
        """
        e1, e2 = np.broadcast_arrays(np.asarray(e1, dtype=float), np.asarray(e2, dtype=float))
        r = np.hypot(e1, e2)
        ok = (r > 0) & (r < 1.0)
        g = np.zeros(r.shape)
        rr = r[ok]
        p = np.exp(self._log_f(rr) - self._log_norm)
        g[ok] = p * self._dlogf_dr(rr) / rr
        return g * e1, g * e2

    def radial_pdf(self, r: np.ndarray | float) -> np.ndarray:
        """1-D density of ``|e|``, ``2 pi |e| P(|e|)`` (paper section 3.1), per unit ``|e|``."""
        r = np.asarray(r, dtype=float)
        return 2.0 * np.pi * r * self.pdf(r, np.zeros_like(r))

    def grid_pdf(self) -> np.ndarray:
        """:meth:`pdf` on :attr:`egrid`, shape ``(n_e,)``; sums to ``1 / de^2``."""
        return self.pdf(self.egrid[:, 0], self.egrid[:, 1])

    def sample(self, n: int, *, rng: np.random.Generator) -> np.ndarray:
        """Draw ellipticities from the continuous prior.

        ``|e|`` is drawn by inverse CDF of ``2 pi |e| P(|e|)`` tabulated on a fine radial
        grid (20,001 points on ``[0, 1]``), the angle ``2 phi`` uniformly.

        Parameters
        ----------
        n : int
            Number of draws.
        rng : numpy.random.Generator
            Random generator (explicit, for reproducibility).

        Returns
        -------
        numpy.ndarray
            ``(n, 2)`` array of ``(e1, e2)``.
        """
        rgrid = np.linspace(0.0, 1.0, 20001)
        dens = np.zeros_like(rgrid)
        dens[:-1] = self.radial_pdf(rgrid[:-1])
        cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(rgrid))])
        cdf /= cdf[-1]
        r = np.interp(rng.random(n), cdf, rgrid)
        phi = rng.uniform(0.0, 2.0 * np.pi, n)
        return np.column_stack([r * np.cos(phi), r * np.sin(phi)])

    # -- persistence ------------------------------------------------------------------
    def form_dict(self) -> dict[str, Any]:
        """The form and its parameters (``form`` and ``B, C, D`` or ``coef``)."""
        raise NotImplementedError

    def on_grid(self, egrid: np.ndarray) -> RadialPrior:
        """The same prior normalised on another grid ``egrid`` (``(n_e, 2)``)."""
        d = self.form_dict()
        return type(self)(**{k: d[k] for k in self._KEYS}, egrid=egrid, method=self.method,
                          history=self.history, info=self.info)  # fmt: skip

    def header_cards(self) -> list[tuple[str, float | str, str]]:
        """``(keyword, value, comment)`` FITS cards that describe the prior."""
        raise NotImplementedError

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (form, parameters, grid step, method, history, info)."""
        d: dict[str, Any] = {
            **self.form_dict(),
            "step": self.step,
            "method": self.method,
            "history": self.history,
            "info": jsonable(self.info),
        }
        std = ellipticity_grid(self.step)
        if std.shape != self.egrid.shape or not np.allclose(std, self.egrid, atol=1e-12):
            d["egrid"] = self.egrid.tolist()
        return d

    def save(self, path: str | Path) -> None:
        """Write the prior to a small JSON file (parameters, grid step, history)."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=1))

    @classmethod
    def load(cls, path: str | Path) -> RadialPrior:
        """Read a prior written by :meth:`save` (either form).

        Raises
        ------
        ValueError
            One line naming the file: unreadable, not JSON, or not a prior.
        """
        return cls.from_dict(read_json(path), source=str(path))

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str = "prior dict") -> RadialPrior:
        """The prior of :meth:`to_dict`, of the form it names (``"form"``; functional
        where absent).

        Parameters
        ----------
        d : dict
            The functional form's ``B``, ``C``, ``D`` or the spline's ``coef``, and
            ``step`` (or ``egrid``); optionally ``method``, ``history`` and ``info``.
        source : str
            What ``d`` came from (a file name), for the error message.

        Raises
        ------
        ValueError
            One line naming ``source`` if ``d`` is not a prior.
        """
        what = f"{source}: not an ellipticity prior"
        if not isinstance(d, dict):
            raise ValueError(f"{what} (a JSON {json_kind(d)}; a prior holds B, C, D and step "
                             "or coef and step)")  # fmt: skip
        form = d.get("form", _DEFAULT_FORM)
        if form not in _FORMS or (cls is not RadialPrior and _FORMS[form] is not cls):
            raise ValueError(f"{what} of form {cls.form!r} (form {form!r})")
        kind = _FORMS[form]
        need = f"a {form} prior holds {', '.join(kind._KEYS)} and step"
        missing = [k for k in kind._KEYS if k not in d]
        if "step" not in d and "egrid" not in d:
            missing.append("step")
        if missing:
            hint = other_file_hint(d, {"priors": "priors", "size_prior": "size prior"})
            raise ValueError(f"{what} (no entry {', '.join(map(repr, missing))}; {need}{hint})")
        try:
            egrid = np.asarray(d["egrid"], dtype=float) if "egrid" in d else None
            if egrid is not None:
                egrid = check_egrid(egrid)
            return kind(
                **{k: d[k] for k in kind._KEYS},
                step=None if egrid is not None else d["step"],
                egrid=egrid,
                method=str(d.get("method", "fixed")),
                history=d.get("history") or [],
                info=d.get("info") or {},
            )
        except (TypeError, ValueError) as err:
            raise ValueError(f"{what} ({err})") from None
