"""The calibration (L0 vocabulary, torch-free): the file's value and loader, and the active one.

The file (`calibration.toml`) is versioned, self-describing and validated on load. What the daemon
takes from it: per-colour `PhaseCurve`s and the phase sign (coding), the per-colour focus offsets
(digital refocus), the depth -> stage mapping (focus), the per-colour intensity (amplitude
compensation), the source's amplitude profile (`[source]`: a Gaussian per colour, the daemon
divides the target amplitude by it) and the relay's aberrations (`[aberration]`: Zernike
coefficients, the daemon pre-compensates them). `[zero_order]` records the coherent unmodulated
light. A part the data could not determine is written `fitted = false` with the reason, never a
guess. Units follow the keys: `_m`, `_mm`, `_rad`, `_deg`, `_px`. Colours are R, G, B.

The active calibration is a value, a `CalibrationStore`: the file a configuration names, loaded
once per file version (a hot swap), which the daemon, the frame worker or a command builds and
hands to every part that applies it; `check_calibration_file` opens it as `nhfd serve` will, for
`nhfd config check`. `nhfd.calib` writes these files (capture, fit, report); this module only reads
them, so everything that applies a calibration stays free of torch.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import math
import numbers
import threading
import tomllib
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from nhfd import spec
from nhfd.config import ConfigError
from nhfd.spec import PhaseCurve

if TYPE_CHECKING:
    from nhfd.config import Config, SLMSettings

FORMAT = "nhfd-calibration"
FORMAT_VERSION = 1


# How far a calibration's bench (`[bench]`) may differ from the configured one and still be
# applied, relative. Wavelength 0.5 %: about 3 nm at 660 nm, the spread between diodes of one
# type and over their temperature range; it moves the fitted phase tables by 0.5 % of their
# stroke, below the fit's own table error (1.4 to 2.2 % RMS). A calibration for another laser
# (1064 nm against 660 nm: 61 %) is far outside. Pitch 0.1 %: a panel's pitch is a design
# constant, so anything beyond rounding is another panel (3.74 um against 8 um: 53 %).
WAVELENGTH_REL_TOL = 5e-3
PITCH_REL_TOL = 1e-3


# The most unmodulated light a calibration may record (intensity fraction): a panel that leaves
# more than half its light unmodulated is not a phase modulator, and a fraction near 1 would make
# the bench models' relative amplitude sqrt(f / (1 - f)) unbounded.
MAX_UNMODULATED_FRACTION = 0.5


class CalibrationFileError(ValueError):
    """A calibration file is missing, corrupt, foreign, from an unknown version, or fitted for
    another bench (other wavelengths or pitch than the configured ones)."""


@dataclass(frozen=True)
class Calibration:
    """One fitted calibration (calibration.toml's value): per-colour phase tables (256 values,
    rad), focus offsets (m), stage mapping (mm), geometry, intensity and the optional source,
    zero-order and aberration fits, with standard errors. Raises ValueError when a value is out of
    range."""

    wavelengths_m: tuple[float, float, float]
    pitch_m: float
    phase_sign: int
    phase_tables_rad: tuple[tuple[float, ...], ...]
    phase_table_std_rad: tuple[float, ...]
    stage_scale: float
    stage_scale_std: float
    stage_at_slm_mm: float
    stage_at_slm_std_mm: float
    z_offset_m: tuple[float, float, float]
    z_offset_std_m: tuple[float, float, float]
    magnification: float
    magnification_std: float
    rotation_deg: float
    rotation_std_deg: float
    mirror_x: bool
    shift_px: tuple[float, float]
    intensity: tuple[float, ...]
    intensity_std: tuple[float, ...]
    residuals: dict[str, Any] = field(default_factory=dict)
    fitted_on: dict[str, Any] = field(default_factory=dict)
    # The illumination per colour (nhfd.calib.response.fit_source): 1/e^2 intensity radius and
    # centre (x, y) on the SLM plane, metres; () = not fitted.
    source_waist_m: tuple[float, ...] = ()
    source_waist_std_m: tuple[float, ...] = ()
    source_centre_m: tuple[tuple[float, float], ...] = ()
    source_centre_std_m: tuple[tuple[float, float], ...] = ()
    # Coherent unmodulated light per colour (zero-order leakage and gap light): intensity fraction
    # of the light leaving the panel, and its phase against grey 0's; () = not fitted.
    unmodulated_fraction: tuple[float, ...] = ()
    unmodulated_fraction_std: tuple[float, ...] = ()
    unmodulated_phase_rad: tuple[float, ...] = ()
    # Relay aberrations: Zernike coefficients for Noll j = 5, 6, ... (radians at
    # zernike_wavelength_m; pupil radius = the aperture's cutoff, see
    # nhfd.optics.pupil.pupil_phase); () = not fitted.
    zernike_rad: tuple[float, ...] = ()
    zernike_std_rad: tuple[float, ...] = ()
    zernike_wavelength_m: float = 0.0
    # What the fit refused to determine, and why.
    refused: tuple[str, ...] = ()
    # The learned bench on top of this fit (`nhfd calib learn`, docs/learned_bench.md): its
    # safetensors file, a name beside the calibration file, and that file's SHA-256 (hex);
    # "" = none (the parametric model alone).
    learned_file: str = ""
    learned_sha256: str = ""
    created: str = ""
    source: str = ""  # the file it was loaded from ("" when fitted in this process)

    def __post_init__(self) -> None:
        if self.phase_sign not in (1, -1):
            raise ValueError(f"phase_sign = {self.phase_sign!r}: must be +1 or -1")
        for name in ("stage_scale", "magnification", "pitch_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} = {v!r}: must be finite and > 0")
        for name in ("stage_at_slm_mm", "rotation_deg"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} = {getattr(self, name)!r}: must be finite")
        if len(self.phase_tables_rad) != 3 or len(self.z_offset_m) != 3 or \
                len(self.intensity) != 3:
            raise ValueError("phase tables, z offsets and intensities: need one per colour")
        for c, t in enumerate(self.phase_tables_rad):
            if len(t) != 256:
                raise ValueError(f"phase table {c}: {len(t)} values, need 256")
            PhaseCurve(tuple(t))  # finite and strictly increasing, or ValueError
        for c, (z, k) in enumerate(zip(self.z_offset_m, self.intensity, strict=True)):
            if not math.isfinite(z) or abs(z) > 0.05:
                raise ValueError(f"z_offset_m[{c}] = {z!r}: must be finite, |z| <= 0.05 m")
            if not (math.isfinite(k) and k > 0):
                raise ValueError(f"intensity[{c}] = {k!r}: must be finite and > 0")
        if self.unmodulated_fraction or self.unmodulated_phase_rad:
            if len(self.unmodulated_fraction) != 3 or len(self.unmodulated_phase_rad) != 3:
                raise ValueError("zero_order: need one unmodulated_fraction and one phase_rad "
                                 "per colour")
            for c, (f, ph) in enumerate(zip(self.unmodulated_fraction,
                                            self.unmodulated_phase_rad, strict=True)):
                if not 0 <= f <= MAX_UNMODULATED_FRACTION:
                    raise ValueError(f"zero_order.unmodulated_fraction[{c}] = {f!r}: must be in "
                                     f"0..{MAX_UNMODULATED_FRACTION} (the bench models add it "
                                     "to every frame)")
                if not math.isfinite(ph):
                    raise ValueError(f"zero_order.phase_rad[{c}] = {ph!r}: must be finite")
        if self.learned_file or self.learned_sha256:
            name = self.learned_file
            if not name or "/" in name or "\\" in name or name.startswith(".") or \
                    not name.endswith(".safetensors"):
                raise ValueError(f"learned.file = {name!r}: must be a file name beside the "
                                 "calibration ending in .safetensors (no folders, not hidden)")
            if len(self.learned_sha256) != 64 or \
                    any(ch not in "0123456789abcdef" for ch in self.learned_sha256):
                raise ValueError(f"learned.sha256 = {self.learned_sha256!r}: must be 64 "
                                 "lower-case hex digits")

    # -- what the daemon uses ------------------------------------------------------------------

    def phase_curves(self) -> list[PhaseCurve]:
        """The fitted phase curves, R, G, B."""
        return [PhaseCurve(tuple(t)) for t in self.phase_tables_rad]

    def relative_intensity(self) -> tuple[float, float, float]:
        """Per-colour intensity relative to green."""
        g = self.intensity[1]
        return tuple(k / g for k in self.intensity)  # type: ignore[return-value]

    def amplitude_gain(self) -> tuple[float, float, float]:
        """Per-colour amplitude factors (<= 1) that equalise the colours' intensity: the
        brightest colour is attenuated to the dimmest."""
        k_min = min(self.intensity)
        return tuple(math.sqrt(k_min / k) for k in self.intensity)  # type: ignore[return-value]

    def source_amplitude(self, panel_hw: tuple[int, int], colour: int) -> np.ndarray:
        """The fitted illumination's amplitude [H, W] on a panel of `panel_hw` pixels, scaled so
        the mean intensity over the panel is 1 (so it never trades against the per-colour
        intensity and exposure); all ones where the source was not fitted."""
        h, w = panel_hw
        if not self.source_waist_m:
            return np.ones((h, w))
        x = (np.arange(w) - (w - 1) / 2) * self.pitch_m - self.source_centre_m[colour][0]
        y = (np.arange(h) - (h - 1) / 2) * self.pitch_m - self.source_centre_m[colour][1]
        intensity = np.exp(-2 * (x[None, :] ** 2 + y[:, None] ** 2)
                           / self.source_waist_m[colour] ** 2)
        return np.sqrt(intensity / intensity.mean())

    def stage_mm_for(self, z_m: float, colour: int = 1) -> float:
        """The stage reading at which colour `colour` images distance `z_m` from the SLM."""
        if not math.isfinite(z_m):
            raise ValueError(f"z_m = {z_m!r}: must be finite")
        return self.stage_at_slm_mm + (z_m - self.z_offset_m[colour]) / self.stage_scale * 1e3

    def refocus_m(self, colour: int) -> float:
        """Digital refocus per colour that puts every colour's focus where green's is. Where the
        camera sees green's plane z, it sees colour c's plane z + (offset_c - offset_G)
        (`z_m(stage, c)`): content of colour c shown that much further from the SLM is seen
        in focus together with green's."""
        return self.z_offset_m[colour] - self.z_offset_m[1]

    def learned_path(self) -> Path | None:
        """The learned bench's weights file (beside the calibration file it was loaded from),
        or None when the calibration has none."""
        if not self.learned_file:
            return None
        return (Path(self.source).parent if self.source else Path(".")) / self.learned_file

    @property
    def label(self) -> str:
        """The file it came from and when it was fitted, for status and logs."""
        return f"{self.source or '(unsaved)'} fitted {self.created or 'now'}"

    # -- file ----------------------------------------------------------------------------------

    def to_toml(self) -> str:
        """The calibration.toml text (format, version, creation time and every section)."""
        created = self.created or _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
        doc: dict[str, Any] = {
            "format": FORMAT, "version": FORMAT_VERSION, "created": created,
            "bench": {"wavelengths_m": list(self.wavelengths_m), "pitch_m": self.pitch_m},
            "phase": {"sign": self.phase_sign,
                      "table_std_rad": list(self.phase_table_std_rad),
                      "R_rad": list(self.phase_tables_rad[0]),
                      "G_rad": list(self.phase_tables_rad[1]),
                      "B_rad": list(self.phase_tables_rad[2])},
            "depth": {"stage_scale": self.stage_scale, "stage_scale_std": self.stage_scale_std,
                      "stage_at_slm_mm": self.stage_at_slm_mm,
                      "stage_at_slm_std_mm": self.stage_at_slm_std_mm,
                      "z_offset_m": list(self.z_offset_m),
                      "z_offset_std_m": list(self.z_offset_std_m)},
            "geometry": {"magnification": self.magnification,
                         "magnification_std": self.magnification_std,
                         "rotation_deg": self.rotation_deg,
                         "rotation_std_deg": self.rotation_std_deg,
                         "mirror_x": self.mirror_x, "shift_px": list(self.shift_px)},
            "intensity": {"per_second": list(self.intensity),
                          "per_second_std": list(self.intensity_std)},
            "source": ({"fitted": True, "waist_m": list(self.source_waist_m),
                        "waist_std_m": list(self.source_waist_std_m),
                        "centre_m": [list(v) for v in self.source_centre_m],
                        "centre_std_m": [list(v) for v in self.source_centre_std_m],
                        "profile": "Gaussian intensity exp(-2 r^2 / waist^2) per colour, "
                                   "normalised to mean 1 over the panel"}
                       if self.source_waist_m else {"fitted": False}),
            "zero_order": ({"fitted": True, "unmodulated_fraction": list(self.unmodulated_fraction),
                            "unmodulated_fraction_std": list(self.unmodulated_fraction_std),
                            "phase_rad": list(self.unmodulated_phase_rad)}
                           if self.unmodulated_fraction else {"fitted": False}),
            "aberration": ({"fitted": True, "first_noll": 5, "zernike_rad": list(self.zernike_rad),
                            "zernike_std_rad": list(self.zernike_std_rad),
                            "wavelength_m": self.zernike_wavelength_m,
                            "pupil": "rho = |f| / aperture cutoff (cycles per SLM pixel)"}
                           if self.zernike_rad else {"fitted": False}),
            **({"learned": {"file": self.learned_file, "sha256": self.learned_sha256,
                            "format": "safetensors (docs/learned_bench.md)"}}
               if self.learned_file else {}),
            "refused": {"reasons": list(self.refused)},
            "residuals": dict(self.residuals),
            "fitted_on": dict(self.fitted_on),
        }
        return _dump(doc)

    def save(self, path: Path | str) -> Path:
        """Write calibration.toml to `path` atomically (a temporary file, then a rename)."""
        path = Path(path)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(self.to_toml())
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path: Path | str) -> Calibration:
        """Read and validate a calibration.toml; `CalibrationFileError` when the file is missing,
        corrupt, foreign, of another version or has a value out of range."""
        path = Path(path)
        if not path.is_file():
            raise CalibrationFileError(f"calibration file {path}: not found")
        try:
            doc = tomllib.loads(path.read_text())
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise CalibrationFileError(f"calibration file {path}: corrupt ({exc})") from None
        if doc.get("format") != FORMAT:
            raise CalibrationFileError(f"calibration file {path}: not an nhfd calibration "
                                       f"(format = {doc.get('format')!r})")
        if doc.get("version") != FORMAT_VERSION:
            raise CalibrationFileError(f"calibration file {path}: version "
                                       f"{doc.get('version')!r}, this nhfd reads "
                                       f"{FORMAT_VERSION}")
        try:
            ph, dp, ge, it = doc["phase"], doc["depth"], doc["geometry"], doc["intensity"]
            return cls(
                wavelengths_m=tuple(doc["bench"]["wavelengths_m"]),
                pitch_m=doc["bench"]["pitch_m"],
                phase_sign=ph["sign"],
                phase_tables_rad=tuple(tuple(ph[f"{c}_rad"]) for c in "RGB"),
                phase_table_std_rad=tuple(ph["table_std_rad"]),
                stage_scale=dp["stage_scale"], stage_scale_std=dp["stage_scale_std"],
                stage_at_slm_mm=dp["stage_at_slm_mm"],
                stage_at_slm_std_mm=dp["stage_at_slm_std_mm"],
                z_offset_m=tuple(dp["z_offset_m"]),
                z_offset_std_m=tuple(dp["z_offset_std_m"]),
                magnification=ge["magnification"], magnification_std=ge["magnification_std"],
                rotation_deg=ge["rotation_deg"], rotation_std_deg=ge["rotation_std_deg"],
                mirror_x=ge["mirror_x"], shift_px=tuple(ge["shift_px"]),
                intensity=tuple(it["per_second"]), intensity_std=tuple(it["per_second_std"]),
                residuals=doc.get("residuals", {}), fitted_on=doc.get("fitted_on", {}),
                **_optional(doc),
                created=str(doc.get("created", "")), source=str(path),
            )
        except (KeyError, TypeError) as exc:
            raise CalibrationFileError(f"calibration file {path}: missing or malformed key "
                                       f"{exc}") from None
        except ValueError as exc:
            raise CalibrationFileError(f"calibration file {path}: {exc}") from None


def unmodulated_amplitude(fraction: float, phase_rad: float) -> complex:
    """The unmodulated light that leaves the panel as a complex amplitude relative to the
    modulated light's unit one, from the flat frames' fit: an intensity `fraction` of all the
    light, at `phase_rad` against grey 0's. A bench model's field leaving the panel is
    `exp(i phase) + this` (the calibration's and refinement's bench models)."""
    return complex(math.sqrt(fraction / (1 - fraction)) * np.exp(-1j * phase_rad))


def check_bench(cal: Calibration, wavelengths_m: tuple[float, ...], pitch_m: float) -> None:
    """Refuse, with `CalibrationFileError` naming the file's field, the expected (configured)
    and the found value, a calibration fitted for other wavelengths or another pixel pitch than
    the bench's: its phase tables, focus offsets and depth mapping belong to other optics.
    Tolerances: `WAVELENGTH_REL_TOL`, `PITCH_REL_TOL`."""
    name = cal.source or "(unsaved)"
    if len(cal.wavelengths_m) != len(wavelengths_m):
        raise CalibrationFileError(f"calibration file {name}: bench.wavelengths_m has "
                                   f"{len(cal.wavelengths_m)} values, expected "
                                   f"{len(wavelengths_m)} (R, G, B)")
    checks = [(f"bench.wavelengths_m[{c}]", want, got, WAVELENGTH_REL_TOL,
               f"optics.wavelengths_nm[{c}]")
              for c, (want, got) in enumerate(zip(wavelengths_m, cal.wavelengths_m, strict=True))]
    checks.append(("bench.pitch_m", pitch_m, cal.pitch_m, PITCH_REL_TOL, "slm.pitch_um"))
    for field_name, want, got, tol, key in checks:
        if not abs(got - want) <= tol * abs(want):  # NaN fails too
            raise CalibrationFileError(
                f"calibration file {name}: {field_name} = {got:.6g} m, expected {want:.6g} m "
                f"(from {key}) within {tol:.1%}: fitted for another bench")


def _optional(doc: dict[str, Any]) -> dict[str, Any]:
    """The sections a fit may leave out (`fitted = false`), as constructor arguments."""
    out: dict[str, Any] = {}
    src = doc.get("source", {})
    if src.get("fitted"):
        out.update(source_waist_m=tuple(src["waist_m"]),
                   source_waist_std_m=tuple(src["waist_std_m"]),
                   source_centre_m=tuple(tuple(v) for v in src["centre_m"]),
                   source_centre_std_m=tuple(tuple(v) for v in src["centre_std_m"]))
    zo = doc.get("zero_order", {})
    if zo.get("fitted"):
        out.update(unmodulated_fraction=tuple(zo["unmodulated_fraction"]),
                   unmodulated_fraction_std=tuple(zo["unmodulated_fraction_std"]),
                   unmodulated_phase_rad=tuple(zo["phase_rad"]))
    ab = doc.get("aberration", {})
    if ab.get("fitted"):
        if ab.get("first_noll", 5) != 5:
            raise ValueError(f"aberration first_noll = {ab.get('first_noll')!r}: need 5")
        out.update(zernike_rad=tuple(ab["zernike_rad"]),
                   zernike_std_rad=tuple(ab["zernike_std_rad"]),
                   zernike_wavelength_m=float(ab["wavelength_m"]))
    out["refused"] = tuple(doc.get("refused", {}).get("reasons", ()))
    learned = doc.get("learned")
    if learned is not None:
        out.update(learned_file=str(learned["file"]), learned_sha256=str(learned["sha256"]))
    return out


# -- a minimal TOML writer (tomllib reads; the standard library has no writer) ------------------

def _value(v: Any) -> str:
    if isinstance(v, bool | np.bool_):
        return "true" if v else "false"
    if isinstance(v, numbers.Integral):
        return str(int(v))
    if isinstance(v, numbers.Real):  # numpy scalars too
        if not math.isfinite(v):
            raise ValueError(f"cannot write {v!r} to a calibration file")
        return repr(float(v))
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _dump(doc: dict[str, Any], prefix: str = "") -> str:
    lines = [f"{k} = {_value(v)}" for k, v in doc.items() if not isinstance(v, dict)]
    out = "\n".join(lines) + ("\n" if lines else "")
    for k, v in doc.items():
        if isinstance(v, dict):
            name = f"{prefix}{k}"
            out += f"\n[{name}]\n" + _dump(v, f"{name}.")
    return out


def fingerprint(cal: Calibration) -> str:
    """SHA-256 (hex) over a calibration's fitted values (every field but `source`, where it was
    loaded from): the same fit gives the same fingerprint wherever its file lies. A tuned model
    records the fingerprint of the calibration it was tuned for (`tuned_for`)."""
    values = asdict(cal)
    values.pop("source", None)
    # The learned bench counts by its bytes' hash, not its name; without one the fingerprint
    # is what it was before calibrations could have one.
    values.pop("learned_file", None)
    if not values.get("learned_sha256"):
        values.pop("learned_sha256", None)
    return hashlib.sha256(json.dumps(values, sort_keys=True, default=str).encode()).hexdigest()


def parametric_fingerprint(cal: Calibration) -> str:
    """The fingerprint of `cal`'s parametric fit alone (its learned bench left out): what a
    learned bench records it was learned on top of."""
    return fingerprint(replace(cal, learned_file="", learned_sha256=""))


# What a tuned model records of the bench it was tuned for (its metadata's `tuned_for`, beside
# the tuning's own figures), and what `status` shows of it.
BENCH_RECORD_KEYS = ("calibration", "calibration_sha256", "date")


def bench_record(cal: Calibration, date: str) -> dict[str, str]:
    """The `BENCH_RECORD_KEYS` of a model tuned for `cal` on `date` (ISO 8601): the
    calibration's label, its fingerprint, the date."""
    return dict(zip(BENCH_RECORD_KEYS, (cal.label, fingerprint(cal), date), strict=True))


def other_bench(tuned_for: Mapping[str, Any] | None, cal: Calibration | None) -> str | None:
    """Why a model tuned for one bench does not fit the calibration `cal` in use (None: it fits,
    or the model was not tuned, `tuned_for` None): the message names both, the model's by its
    calibration's label, fingerprint and date."""
    if not tuned_for:
        return None
    want = str(tuned_for.get("calibration_sha256", ""))
    have = fingerprint(cal) if cal is not None else None
    if have == want:
        return None
    theirs = (f"calibration {tuned_for.get('calibration', '?')} (fitted values {want[:12]}, "
              f"tuned {tuned_for.get('date', '?')})")
    ours = (f"calibration {cal.label} (fitted values {have[:12]})" if cal is not None and have
            else "no calibration (calibration.file is empty)")
    return f"the model was tuned for {theirs}; this bench applies {ours}"


def panel_coding(slm: SLMSettings, cal: Calibration | None
                 ) -> tuple[tuple[PhaseCurve, ...], int, bool]:
    """The phase curves, sign and grey inversion frames are coded with, for the configuration's
    `[slm]` section: a calibration's measured curves and sign replace the configured ones. The
    one rule for the blank panel (`nhfd.daemon.panel`) and for frames (`nhfd.pipeline.settings`),
    so the zero pattern around a frame is the frame's own zero."""
    curves = spec.phase_curves(slm.phase_stroke_rad, cal.phase_tables_rad if cal else ())
    return tuple(curves), int(cal.phase_sign if cal else slm.phase_sign), bool(slm.grey_invert)


# The active calibration: the file a configuration names (`[calibration] file`), loaded once per
# file version by the `CalibrationStore` the daemon (or a command) builds and hands to each part
# that applies it. A configured file that cannot be loaded, or that was fitted for another bench
# (`check_bench`: other wavelengths or pitch than the configuration's), raises
# `CalibrationFileError` naming it: a bench silently running uncalibrated, or on another bench's
# tables, is worse than a daemon that says why it will not start.
#
# When the file changes on disk after a version of it was accepted (a hot swap), a new version
# that is refused does not replace the accepted one: it stays in use, and `refusal` says why the
# file on disk is not (the daemon shows it in `status`). The first load has nothing to keep, so it
# raises: `nhfd serve` and `nhfd config check` refuse the file.
log = logging.getLogger("nhfd.calibration")

# A version no file has (`CalibrationStore(accepted=...)`): the file on disk is still read, and
# refused or accepted, at the first look.
_NOT_LOOKED = (-2, -2, -2)


def _version(path: Path) -> tuple[int, int, int]:
    try:
        st = path.stat()
    except OSError:
        return (-1, -1, -1)
    return (st.st_ino, st.st_mtime_ns, st.st_size)


class CalibrationStore:
    """The calibration one configuration names, as a value: built once by whoever owns the bench
    (`nhfd serve`, a command, the frame worker) and handed to every part that applies it.

    `path`: the calibration file, or None (`calibration.file` empty: `active()` is None).
    `wavelengths_m`, `pitch_m`: the configured bench (`[optics]` wavelengths, `[slm]` pitch); a
    file fitted for another is refused. `accepted`: a calibration already accepted elsewhere (the
    frame worker gets the daemon's at its start), kept when the file on disk is refused by the
    first look. Thread-safe: the daemon's loop and the worker's threads share one store."""

    def __init__(self, path: str | Path | None, wavelengths_m: tuple[float, ...], pitch_m: float,
                 accepted: Calibration | None = None) -> None:
        self.path = Path(path) if path else None
        self.wavelengths_m = tuple(float(w) for w in wavelengths_m)
        self.pitch_m = float(pitch_m)
        self._lock = threading.Lock()
        self._version = _NOT_LOOKED
        self._good = accepted if self.path is not None else None
        self._refused: str | None = None
        self._reported = False

    @classmethod
    def of(cls, config: Config, accepted: Calibration | None = None) -> CalibrationStore:
        """The store for `config`: `[calibration] file`, checked against `[optics]` wavelengths
        and `[slm]` pitch. `accepted`: as the constructor's."""
        return cls(config.calibration.file or None, tuple(config.optics.wavelengths_m),
                   config.slm.pitch_m, accepted)

    def _look(self) -> None:
        """Load the file when its version changed since the last look (under the lock)."""
        if self.path is None:
            return
        version = _version(self.path)
        if version == self._version:
            return
        try:
            cal = Calibration.load(self.path)  # raises CalibrationFileError with the path
            check_bench(cal, self.wavelengths_m, self.pitch_m)
        except CalibrationFileError as exc:
            if self._good is None:
                raise
            log.warning("%s; keeping %s", exc, self._good.label)
            self._refused = f"{exc}; keeping {self._good.label}"
            self._reported = False
        else:
            self._good, self._refused = cal, None
        self._version = version

    def active(self) -> Calibration | None:
        """The calibration in use (the file's newest accepted version), or None when none is
        configured; raises `CalibrationFileError` when no version was ever accepted."""
        with self._lock:
            self._look()
            return self._good

    def refusal(self) -> str | None:
        """Why the file, as it is on disk now, is not the calibration in use (a refused hot swap:
        the earlier version is kept), or None."""
        with self._lock:
            self._look()
            return self._refused

    def new_refusal(self) -> str | None:
        """`refusal`, but only the first time it is asked for that file version: for an error
        list that should say it once."""
        with self._lock:
            self._look()
            if self._refused is None or self._reported:
                return None
            self._reported = True
            return self._refused


def check_calibration_file(config: Config, origin: str) -> CalibrationStore:
    """Open the calibration file `config` names as `nhfd serve` does at start (the one file a
    configuration names that the daemon reads then), raising `ConfigError` with the loader's
    reason and `origin` (the configuration file); the store, for the caller to keep."""
    store = CalibrationStore.of(config)
    try:
        store.active()
    except ValueError as exc:
        reason = " ".join(str(exc).split())  # one line, whatever the parser said
        raise ConfigError(f"{origin}: calibration.file = {config.calibration.file!r}: "
                          f"{reason}") from None
    return store
