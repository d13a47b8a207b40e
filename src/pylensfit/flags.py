"""Per-object bit flags with a name table (every catalogue row carries one).

A row with ``flags == 0`` was measured and is usable for shear. Any other value says
why not; several reasons may be set at once. ``STAR`` is informational (the object
was measured, and its most likely size is 0).
"""

from __future__ import annotations

import numpy as np

__all__ = ["BAD", "FLAGS", "METACAL_FLAGS", "describe", "flag_value"]

#: name -> (bit value, description)
FLAGS: dict[str, tuple[int, str]] = {
    "STAR": (1, "most likely model size is 0 or below Config.point_source_size: a point source"),
    "FIT_FAILED": (2, "likelihood not finite on the whole grid (NaN, or a range beyond "
                   "float32's: a stamp of absurd values), or no finite shape from it"),
    "BAD_PIXELS": (4, "non-finite pixels in the stamp"),
    "BAD_NOISE": (8, "noise sigma not finite and positive"),
    "NO_PEAK": (16, "no positive cross-correlation peak near the catalogue position"),
    "EDGE": (32, "stamp crosses the image edge"),
    "CLOSE_PAIR": (64, "another detected object inside the stamp"),
    "MASKED": (128, "masked or zero-weight pixels in the stamp"),
    "PSF_FAILED": (256, "no usable PSF for this object"),
    "NOT_MEASURED": (512, "not attempted"),
    "LOW_SNR": (1024, "measured, but the best model's S/N is below Config.min_snr, or (an "
                "input catalogue's row) the S/N at the catalogue position itself is below "
                "the threshold of false-alarm probability Config.forced_false_alarm: most "
                "such rows are noise"),
    "BAD_POSITION": (2048, "the input catalogue's position is not finite (NaN or inf): the "
                     "row is kept, with NaN positions, and not measured"),
    "DEFECT": (4096, "the best model does not fit the stamp (a residual of reduced "
               "chi-square above Config.max_reduced_chi2 and above "
               "Config.max_residual_fraction of the model's power, or no finite "
               "amplitude): most such objects are image defects (a saturated star, a bleed "
               "trail, a satellite, a hot pixel); its model is subtracted neither from its "
               "neighbours nor from the sky"),
    "SATURATED": (8192, "the stamp holds pixels at or above the saturation level "
                  "(Config.saturation, else the image's SATURATE card) or within "
                  "Config.saturation_grow px of one: they are masked (MASKED is set too) "
                  "and the object is not fitted"),
    "PSF_SUSPECT": (16384, "the image's PSF model fails its check on held-out stars: their "
                    "ellipticities differ from the model's by a mean square above "
                    "pipeline.PSF_SUSPECT_CHI2 times their noise's, beyond chance "
                    "(pipeline.PSF_SUSPECT_PVALUE; most often galaxies taken for stars); "
                    "the object is measured with it all the same"),
}

#: name -> (bit value, description) of the ``mcal_flags`` column of a catalogue measured
#: with ``Config.response = "metacal"``: one bit per metacalibration image whose fit a
#: selection of that image's branch leaves out, and one for a row not metacalibrated
METACAL_FLAGS: dict[str, tuple[int, str]] = {
    "noshear": (1, "the unsheared image's fit is not usable (no finite ln L row, a fit "
                "flag) or is a point source"),
    "1p": (2, "as noshear, the image sheared by +delta in g1"),
    "1m": (4, "as noshear, the image sheared by -delta in g1"),
    "2p": (8, "as noshear, the image sheared by +delta in g2"),
    "2m": (16, "as noshear, the image sheared by -delta in g2"),
    "NOT_METACALIBRATED": (32, "not metacalibrated: not measured, flagged before the shapes "
                           "(flags other than STAR), or its largest stamp "
                           "(Config.largest_stamp) crosses the image's edge or holds bad "
                           "pixels"),
}

#: flags that make a row unusable for shear
BAD = sum(v for k, (v, _) in FLAGS.items() if k not in ("NO_PEAK",))


def flag_value(*names: str) -> int:
    """The bit mask of the given flag names."""
    try:
        return int(sum(FLAGS[n][0] for n in names))
    except KeyError as err:
        raise ValueError(f"unknown flag {err.args[0]!r}; known: {list(FLAGS)}") from None


def describe(flags: int) -> list[str]:
    """Names of the bits set in ``flags``."""
    f = int(np.asarray(flags))
    return [n for n, (v, _) in FLAGS.items() if f & v]
