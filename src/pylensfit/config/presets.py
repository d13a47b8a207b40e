"""The named configurations: overrides of the defaults, by name."""

from __future__ import annotations

from typing import Any

__all__ = ["PRESETS"]

#: named configurations: ``name -> (overrides of the defaults, description)``
PRESETS: dict[str, tuple[dict[str, Any], str]] = {
    "default": ({}, "the recommended method (Config())"),
    "paper": (
        {"model": "devaucouleurs", "n_bulge_fractions": 1, "max_stamp_size": 0,
         "r_step": 0.2, "r_floor": 0.0, "size_prior": "flat", "size_prior_per_run": False,
         "amplitude_prior": "uniform", "estimate_flux_prior": False,
         "estimate_position_prior": False, "min_snr": 0.0, "prior_form": "functional",
         "psf_model": "constant"},
        "Kitching et al. (2008)'s setup: de Vaucouleurs model, flat size prior, uniform "
        "amplitude prior, 2-pixel position prior, one stacked PSF per image",
    ),
}  # fmt: skip
