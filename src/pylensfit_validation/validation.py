"""The STEP-like validation of the method (paper sections 4-5), gathered: the public
names of the modules that do its parts.

* :mod:`pylensfit_validation.step`: STEP1- and STEP2-like sets simulated with GalSim
  (:func:`simulate_step`, :func:`read_manifest`, :func:`render_step2_field`).
* :mod:`pylensfit_validation.stats`: m and c, Q, the shear of twin pairs and groups, the
  truth's control variate, the spread of the offsets over PSFs, the PSF leakage, bins.
* :mod:`pylensfit_validation.estimates`: a set's catalogues, measured once and kept,
  matched to the truth, and their shear estimates.
* :mod:`pylensfit_validation.validate`: :func:`validate`, m, c, sigma_c and Q per PSF and
  per bin, with the diagnostics of the PSFs and priors.
* :mod:`pylensfit_validation.reports`: :func:`write_report`, the Markdown report and its
  figures.
* :mod:`pylensfit_validation.quick`: :func:`quick_validation`, the quick tier.
"""

from __future__ import annotations

from .estimates import (
    BIN_COLUMNS,
    bins_table,
    check_frame,
    matched_galaxies,
    mc_rows,
    measured_catalogues,
    prior_check,
    set_frame,
    shapes_to_sky,
    shear_estimates,
)
from .quick import (
    QUICK_NGAL,
    QUICK_PRIOR_NGAL,
    quick_validation,
)
from .reports import (
    nan_note,
    write_report,
)
from .stats import (
    BIN_LABELS,
    DEFAULT_BINS,
    MATCH_RADIUS,
    MC_COLUMNS,
    MORPHOLOGY_EDGES,
    PSF_HELDOUT_TARGET,
    TARGETS,
    bin_index,
    c_scatter,
    controlled_estimate,
    fit_m_c,
    fit_m_c_cov,
    group_members,
    group_shear,
    leakage_table,
    mc_summary,
    nanmean,
    psf_leakage,
    quality_factor,
    quantile_edges,
    read_truth,
    shear_groups,
    sky_columns,
    truth_control_variate,
    truth_terms,
    twin_shear,
)
from .step import (
    STEP1_PSFS,
    STEP1_SHEARS,
    STEP2_KINDS,
    STEP2_PSFS,
    read_manifest,
    render_step2_field,
    simulate_step,
    spec_for,
)
from .validate import (
    step_config,
    true_psf_image,
    validate,
)

__all__ = [
    "STEP1_PSFS",
    "STEP1_SHEARS",
    "STEP2_KINDS",
    "STEP2_PSFS",
    "read_manifest",
    "render_step2_field",
    "simulate_step",
    "spec_for",
    "BIN_LABELS",
    "DEFAULT_BINS",
    "MATCH_RADIUS",
    "MC_COLUMNS",
    "MORPHOLOGY_EDGES",
    "PSF_HELDOUT_TARGET",
    "TARGETS",
    "bin_index",
    "c_scatter",
    "controlled_estimate",
    "fit_m_c",
    "fit_m_c_cov",
    "group_members",
    "group_shear",
    "leakage_table",
    "mc_summary",
    "nanmean",
    "psf_leakage",
    "quality_factor",
    "quantile_edges",
    "read_truth",
    "shear_groups",
    "sky_columns",
    "truth_control_variate",
    "truth_terms",
    "twin_shear",
    "BIN_COLUMNS",
    "bins_table",
    "check_frame",
    "matched_galaxies",
    "mc_rows",
    "measured_catalogues",
    "prior_check",
    "set_frame",
    "shapes_to_sky",
    "shear_estimates",
    "step_config",
    "true_psf_image",
    "validate",
    "nan_note",
    "write_report",
    "QUICK_NGAL",
    "QUICK_PRIOR_NGAL",
    "quick_validation",
]
