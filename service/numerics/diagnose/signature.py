"""What is left: the signature of a residual, and the verdict over the candidates in three kinds.

The signature says what a residual looks like without naming an effect:

- shared: how much of the scalar channels' excess over their noise floor is common to all probes (the
  mean covariance of pairs of probes against the mean excess variance). A field change at the site
  (the ambient field varying, traffic) is common to every probe; a probe's own flicker noise, offset
  drift or perming is not;
- differences: whether the difference channels rise above their floor (an effect that differs between
  probes shows there; a uniform field change cancels);
- time scale: the period above which half of the excess power lies, and the slope of the spectrum
  (about -1 for flicker noise, -2 or steeper for a smooth variation);
- follows: the observables that explain most of it (from where_it_fails).

The verdict: "at the floor" (nothing above the noise worth explaining), "explained by X" (adding X brings
the residual within FLOOR_FACTOR of the floor), "partly explained by X" (X is significant, something is
left, described), or "unexplained" (no candidate is significant; what is left is described, with what
would explain it).

Numerics only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from fluxcal.service.numerics.effects.timebase import sample_grid
from fluxcal.service.numerics.engine import FitResult

from .harmonics import band_source, column_lines, harmonic_source
from .where import TURNING_SHARE

FLOOR_FACTOR = 1.3          # a residual within this factor of the noise floor is "at the floor"
#: a channel is left above its own floor where its RMS exceeds the floor by this factor both held out and in the fit
#: itself: "explained" and "at the floor" need every channel within it. A saturating coil's current taken by `column`
#: left s1's scalar channel at 1.42 times its floor held out and 1.26 in the fit, under 1.16 over all channels; every
#: channel of worlds the catalogue explains fully stood within 1.08 (white or 1/f noise). Held out alone would not
#: do: a perming step inside a held-out block is mispredicted there (the block's own step found again without it),
#: and a world hysteresis explains to 1.08 in the fit stood at 1.87 held out (tests/numerics/test_verdict_channels.py)
CHANNEL_FACTOR = 1.15
SHARED = 0.6                # share of the excess common to all probes above which it is called common
OWN = 0.25                  # ... below which each probe's own
FOLLOWS = 0.15              # explained variance above which a residual is said to follow an observable


def _scalar_and_diff(fit: FitResult) -> tuple[list[int], list[int]]:
    pr = fit.problem
    kinds = [pr.channel_probe(c)[0] for c in range(len(fit.channels.names))]
    return ([c for c, k in enumerate(kinds) if k == "scalar"], [c for c, k in enumerate(kinds) if k != "scalar"])


def _shared(values: np.ndarray, noise: np.ndarray) -> float | None:
    """Share of the scalar excess variance common to all probes: mean pair covariance / mean excess."""
    p = values.shape[1]
    if p < 2:
        return None
    r = values - values.mean(0)
    cov = r.T @ r / max(r.shape[0] - 1, 1)
    excess = float(np.mean(np.diag(cov) - noise ** 2))
    if excess <= 0:
        return None
    pairs = cov[np.triu_indices(p, 1)]
    return float(np.clip(np.mean(pairs) / excess, 0.0, 1.0))


LINE_SHARE = 0.5            # a spectral line: this share of the excess power within LINE_BINS bins of its peak
LINE_BINS = 2


def _time_scale(t_s: np.ndarray, y: np.ndarray, noise: float) -> tuple[float | None, float | None, float | None]:
    """(period in s above which half of the excess power lies, spectral slope, frequency of a spectral line
    or None) of a residual, from a Welch spectrum on the interval of effects.timebase.sample_grid (a steady time
    base's median, a bursty one's mean: on the median a real board's bursty record read 4 times too high)."""
    n = y.size
    if n < 256:
        return None, None, None
    dt = sample_grid(t_s)[1]
    nper = int(2 ** np.floor(np.log2(n / 4)))
    from scipy.signal import welch                      # here, not at import (a command's start)

    f, p = welch(y - y.mean(), fs=1.0 / dt, nperseg=nper)
    f, p = f[1:], p[1:]
    white = 2.0 * noise ** 2 * dt                         # one-sided density of the white floor
    excess = np.clip(p - white, 0.0, None)
    if excess.sum() <= 0:
        return None, None, None
    peak = int(np.argmax(excess))
    near = excess[max(0, peak - LINE_BINS):peak + LINE_BINS + 1].sum()
    line = None
    if near >= LINE_SHARE * excess.sum() and peak > LINE_BINS:
        # the peak's frequency to a fraction of a bin: the power-weighted mean over its bins
        sl = slice(peak - LINE_BINS, peak + LINE_BINS + 1)
        line = float(np.sum(f[sl] * excess[sl]) / np.sum(excess[sl]))
    cum = np.cumsum(excess) / excess.sum()
    f_half = float(f[np.searchsorted(cum, 0.5)])
    # slope where the excess stands clearly above the floor
    band = p > 3.0 * white
    slope = None
    if np.count_nonzero(band) >= 4 and np.ptp(np.log(f[band])) > np.log(4.0):
        slope = float(np.polyfit(np.log(f[band]), np.log(p[band]), 1)[0])
    return 1.0 / f_half, (None if line is not None else slope), line


def signature(fit: FitResult, noise: np.ndarray, where: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """The signature of fit's residual (see the module doc), JSON-ready."""
    vals = fit.channels.values
    sc, df = _scalar_and_diff(fit)
    rms = np.sqrt(np.mean(vals ** 2, axis=0))
    out: dict[str, Any] = {}
    if sc:
        out["scalar_rms_nT"] = float(np.sqrt(np.mean(rms[sc] ** 2)))
        out["scalar_noise_nT"] = float(np.sqrt(np.mean(noise[sc] ** 2)))
        out["shared_fraction"] = _shared(vals[:, sc], noise[sc])
    if df:
        out["difference_rms_nT"] = float(np.sqrt(np.mean(rms[df] ** 2)))
        out["difference_noise_nT"] = float(np.sqrt(np.mean(noise[df] ** 2)))
    # the time scale: of the probes' common part when it dominates, else of the channel furthest above its floor
    if sc and (out.get("shared_fraction") or 0.0) >= SHARED:
        y, nz = vals[:, sc].mean(1), float(np.sqrt(np.mean(noise[sc] ** 2) / len(sc)))
    else:
        c = int(np.argmax(rms / noise))
        y, nz = vals[:, c], float(noise[c])
    out["half_power_period_s"], out["spectral_slope"], out["line_hz"] = _time_scale(fit.channels.t_s, y, nz)
    if sc and len(sc) > 1:
        # which probes carry it: each probe's share of the summed scalar excess
        excess = np.clip(rms[sc] ** 2 - noise[sc] ** 2, 0.0, None)
        if excess.sum() > 0:
            names = [fit.channels.names[c].split(".")[0] for c in sc]
            out["probe_share"] = {nm: float(e / excess.sum()) for nm, e in zip(names, excess)}
    seen: dict[str, dict[str, Any]] = {}
    for w in where or []:                      # strongest first; one entry per observable
        if w["strength"] >= FOLLOWS and w["observable"] not in seen:
            seen[w["observable"]] = {"observable": w["observable"], "channel": w["channel"], "strength": w["strength"],
                                     **({"band": w["band"], "band_hz": w.get("band_hz"),
                                         "turning_share": w.get("turning_share")} if w.get("band") else {})}
    out["follows"] = list(seen.values())[:3]
    return out


def _period_text(s: float) -> str:
    return f"{s / 60:.0f} min" if s >= 120 else f"{s:.0f} s" if s >= 2 else f"{s * 1000:.0f} ms"


@dataclass(frozen=True)
class Carried:
    """What the data carry, so that the advice never asks to log it: the probes with a temperature of their own
    and those that borrow another's, the logged columns, a scalar or vector reference, the number of probes, the
    attitude."""

    temperatures: tuple[str, ...] = ()
    borrowed: tuple[str, ...] = ()
    columns: tuple[str, ...] = ()
    reference: bool = False
    vector_reference: bool = False
    probes: int = 1
    attitude: bool = False
    #: each logged column's own spectral lines (harmonics.column_lines), Hz, and the record's length: a line of the
    #: residual that their combinations make is that column's shape, never "no logged column follows it"
    motion: tuple[tuple[str, tuple[float, ...]], ...] = ()
    duration_s: float = 0.0

    @classmethod
    def of(cls, data: Any) -> "Carried":
        """From an EffectData."""
        from fluxcal.service.numerics.effects.column import usable_columns

        own = tuple(n for k, n in enumerate(data.probe_names) if np.isfinite(data.temp_C[:, k]).sum() >= 2)
        borrowed = tuple(n for n in data.probe_names if n not in own) if own else ()
        return cls(temperatures=own, borrowed=borrowed, columns=tuple(usable_columns(data)),
                   reference=data.ref_total_nT is not None, vector_reference=data.ref_vector_nT is not None,
                   probes=data.n_probes, attitude=data.attitude() is not None,
                   motion=tuple((k, tuple(v)) for k, v in column_lines(data).items()), duration_s=data.duration_s)

    @property
    def temperature(self) -> bool:
        return bool(self.temperatures)

    def logged(self) -> str:
        """'heater_A, fan_hz' or 'no column'."""
        return ", ".join(self.columns) if self.columns else "no column"

    def unfollowed(self, followed: set[str]) -> str:
        """'; no logged column (heater_A, fan_hz) follows it' of the logged columns that `followed` (the observables
        the residual follows, as where-it-fails names them) does not hold; '' where none is left."""
        left = [c for c in self.columns if c not in followed and f"{c} x field direction" not in followed]
        return f"no logged column ({', '.join(left)}) follows it" if left else ""

    def harmonic(self, hz: float | None = None, band_hz: Any = None) -> tuple[str, str] | None:
        """(column, how) of a logged column whose own motion makes a line at hz (or puts its lines or their
        combinations in the band band_hz): the residual there is that column's shape, not something unlogged."""
        sources = {k: list(v) for k, v in self.motion}
        if hz is not None:
            return harmonic_source(hz, sources, self.duration_s)
        if band_hz is not None:
            return band_source(tuple(band_hz), sources)
        return None


#: every request to log something the advice can make, by what it asks for; `ask` gives it only where the data do
#: not carry that (tests/numerics/test_advice.py goes over every advice path with every combination)
LOG_ASKS = {
    "temperature": "log the sensors' temperatures",
    "reference": "log a reference magnetometer (a ref_total column)",
    "second probe": "log a second probe or a reference magnetometer",
    "phase": "log the phase or speed of what turns at that rate",
    # "else": beside the columns the data carry, which it follows no more than by chance (a heater's current logged,
    # it read as asking to log a current)
    "column": "log what else might follow it (a current, a voltage, a speed)",
}


def ask(what: str, carried: Carried) -> str | None:
    """The request to log `what` (a key of LOG_ASKS), or None where the data carry it already."""
    have = {"temperature": carried.temperature,
            "reference": carried.reference or carried.vector_reference,
            "second probe": carried.probes > 1 or carried.reference or carried.vector_reference,
            "phase": False, "column": False}[what]
    return None if have else LOG_ASKS[what]


def _either(*options: str | None) -> str:
    """'a, or b' of the options that are not None."""
    got = [o for o in options if o]
    return ", or ".join(got)


def describe(sig: dict[str, Any], carried: "Carried | bool") -> tuple[str, str]:
    """(what is left, what would explain it), one sentence each, from a signature; `carried`: what the data carry
    (a bool: only whether there is a scalar reference, for callers that know nothing else)."""
    if not isinstance(carried, Carried):
        carried = Carried(reference=bool(carried))
    above = sig.get("channels_above") or []
    diff_up = ("difference_rms_nT" in sig
               and (sig["difference_rms_nT"] > FLOOR_FACTOR * sig["difference_noise_nT"]
                    or any(c["family"] != "scalar" for c in above)))
    scalar_up = ("scalar_rms_nT" in sig and (sig["scalar_rms_nT"] > FLOOR_FACTOR * sig["scalar_noise_nT"]
                                             or any(c["family"] == "scalar" for c in above)))
    parts = _left_parts(sig, above, scalar_up, diff_up)
    return "; ".join(parts), _advice(sig, carried, diff_up)


def _left_parts(sig: dict[str, Any], above: list[dict[str, Any]], scalar_up: bool, diff_up: bool) -> list[str]:
    """The phrases of what is left: the channels above their floor, the families, shared or own, the time scale, the
    frames, what it follows."""
    parts: list[str] = []
    shared = sig.get("shared_fraction")
    if above:
        parts.append(channels_text(above))
    if scalar_up:
        parts.append(f"{sig['scalar_rms_nT']:.2f} nT against a {sig['scalar_noise_nT']:.2f} nT floor in the scalar "
                     f"channels")
    if diff_up:
        parts.append(f"{sig['difference_rms_nT']:.2f} nT against {sig['difference_noise_nT']:.2f} nT in the "
                     f"differences")
    elif "difference_rms_nT" in sig:
        parts.append("the differences between probes are at their floor")
    if shared is not None and scalar_up:
        if shared >= SHARED:
            parts.append(f"common to all probes ({100 * shared:.0f} % of the excess is shared)")
        elif shared <= OWN:
            share = sig.get("probe_share") or {}
            top = [nm for nm, v in sorted(share.items(), key=lambda kv: -kv[1]) if v >= 0.2]
            if share and len(top) < len(share):
                parts.append(f"{' and '.join(top)}'s own ({100 * shared:.0f} % shared; {', '.join(top)} "
                             f"{'carries' if len(top) == 1 else 'carry'} "
                             f"{100 * sum(share[t] for t in top):.0f} % of the excess)")
            else:
                parts.append(f"each probe's own ({100 * shared:.0f} % shared)")
        else:
            parts.append(f"partly common to the probes ({100 * shared:.0f} % shared)")
    period, slope, line = sig.get("half_power_period_s"), sig.get("spectral_slope"), sig.get("line_hz")
    if line is not None:
        parts.append(f"a spectral line at {line:.2f} Hz holds most of it")
    elif period is not None:
        slow = f"half of its excess power at periods over {_period_text(period)}"
        if slope is not None:
            slow += f", spectrum ~ f^{slope:.1f} across the band above its floor"
        parts.append(slow)
    if sig.get("frames"):
        parts.append(sig["frames"])
    follows = sig.get("follows") or []
    if follows:
        parts.append("it follows " + ", ".join(
            f"{f['observable']}{' ' + f['band'] if f.get('band') else ''} in {f['channel']} ({100 * f['strength']:.0f} %)"
            for f in follows))
    return parts


#: what would explain a residual that is each probe's own slow noise
FLICKER = ("each probe's own slow noise (flicker, spectrum about 1/f): not a missing effect; it limits slow terms "
           "(drift, temperature) and sets the real floor")


def rest_is_flicker(sig: dict[str, Any], carried: "Carried | bool") -> bool:
    """Whether describe() says of this signature that it is each probe's own slow noise (no missing effect)."""
    return describe(sig, carried)[1] == FLICKER


def _advice(sig: dict[str, Any], carried: Carried, diff_up: bool) -> str:
    """What would explain it: a strong tie to something the data carry first, then a line, a shared or own wander
    (time is no cause: any slow change follows it; whether the change is shared decides first)."""
    shared = sig.get("shared_fraction")
    slope, line = sig.get("spectral_slope"), sig.get("line_hz")
    follows = sig.get("follows") or []
    strong = follows and follows[0]["observable"] not in ("frequency", "time") and follows[0]["strength"] >= 0.5
    if strong:
        advice = _follows_advice(follows[0], carried, follows)
    elif line is not None and carried.harmonic(hz=line) is not None:
        col, how = carried.harmonic(hz=line)
        advice = _shape_advice(col, f"the line at {line:.4g} Hz is {how}")
    elif line is not None:
        unfollowed = carried.unfollowed({f["observable"] for f in follows})
        logged = f"; {unfollowed}" if unfollowed else ""
        advice = (f"something periodic at {line:.2f} Hz (a motor, pump or fan near the probe, a rotating part, an "
                  f"aliased mains harmonic): nothing in the catalogue is periodic{logged}; "
                  + _either(ask("phase", carried), "add an effect of your own with a sine and a cosine at that "
                                                   "frequency (docs/effects.md)"))
    elif shared is not None and shared >= SHARED and not diff_up:
        advice = ("a field change at the site, common to all probes: " +
                  ("the scalar reference does not follow it; check its timing and position" if carried.reference else
                   _either(ask("reference", carried) and ask("reference", carried) + " so the total field follows it",
                           "let the other probes measure it (--effects ambient)")))
    elif shared is not None and shared <= OWN and slope is not None and -1.6 <= slope <= -0.5 and not (
            follows and follows[0]["strength"] >= 2 * FOLLOWS):
        advice = FLICKER
    elif follows and follows[0]["observable"] == "time":
        advice = _time_advice(shared, sig.get("probe_share") or {}, carried)
    elif follows:
        # a band or a time is no cause: a logged column the residual follows nearly as well (half as well or more) is
        # named first (a servo's magnet on a hand-turned board, followed 45 % through the field's direction beside a
        # band at 48 %, was advised to log the phase of something turning)
        made = carried.harmonic(band_hz=follows[0].get("band_hz")) if follows[0].get("band_hz") else None
        logged = [f for f in follows if f["observable"] in carried.columns
                  or f["observable"].endswith(" x field direction")]
        cause = follows[0] if made is not None and _followed(made[0], follows) else next(
            (f for f in logged if f["strength"] >= 0.5 * follows[0]["strength"]), follows[0])
        advice = _follows_advice(cause, carried, follows)
    else:
        carry = [w for w, on in (("temperatures", carried.temperature), ("a reference", carried.reference),
                                 (f"columns ({carried.logged()})", bool(carried.columns))) if on]
        asks = [a for a in (ask("temperature", carried), ask("reference", carried)) if a]
        advice = ("nothing the data carry explains it" + (f" (they carry {', '.join(carry)})" if carry else "") + "; "
                  + _either(*asks, LOG_ASKS["column"]))
    return advice


def _time_advice(shared: float | None, share: dict[str, float], carried: Carried) -> str:
    """A change in time no term follows: what the data already say of whether the field or a sensor changed (a
    second probe and a reference see a change of the field; a user's warm-up of one probe was told to log one)."""
    top = [nm for nm, v in sorted(share.items(), key=lambda kv: -kv[1]) if v >= 0.2]
    unseen_temp = ("a temperature the data do not carry" if not carried.temperature else
                   "a temperature the logged one does not follow, or its lag")
    own = "add an effect of your own (docs/effects.md)"
    if shared is not None and shared <= OWN and top and len(top) < len(share):
        others = "the other probes" + (" and the reference" if carried.reference else "")
        return (f"a change in time of {' and '.join(top)} alone that no term follows (drift's polynomial does not): "
                f"{others} do not see it, so the sensor changed, not the field (a warm-up, an offset settling, "
                f"{unseen_temp}); " + _either(ask("temperature", carried), own))
    if shared is not None and shared <= OWN and len(share) > 1:
        return (f"each probe changes in time on its own ({100 * shared:.0f} % of the excess shared), which no term "
                f"follows (drift's polynomial does not): not a field of the site, which all would see; each sensor's "
                f"slow noise (flicker) or its own slow change (a warm-up, {unseen_temp}): "
                + _either(ask("temperature", carried), "record longer to tell noise from a drift"))
    if shared is not None and shared >= SHARED:
        return ("a change in time common to the probes that no term follows: a change of the field at the site" +
                ("; the scalar reference does not follow it: check its timing and position" if carried.reference else
                 "; " + _either(ask("reference", carried), "try --effects ambient")))
    if carried.probes > 1 or carried.reference or carried.vector_reference:
        return ("a change in time that no term follows (drift's polynomial does not); "
                + _either(ask("temperature", carried), own))
    return ("a change in time that no term follows (drift's polynomial does not): whether the field or the sensor "
            "changed cannot be told without a second probe or a reference magnetometer; "
            + _either(ask("second probe", carried), ask("temperature", carried), own))


#: what a residual that follows an observable suggests, when no catalogue term took it
_ADVICE = {
    "temperature": "a temperature dependence that the temperature and thermal terms do not take (a higher power, "
                   "a delay beyond theirs, or a matrix that follows it): the logged temperature may be far from the "
                   "core",
    "temperature rate": "a dependence on how fast the temperature changes: a core that lags its logged temperature "
                        "(try thermal) or a thermal gradient across the sensor",
    "temperature, delayed": "the temperature with a delay: a core that lags its logged temperature (try thermal)",
    "angular rate": "a dependence on the rotation rate that eddy and lag do not take (a filter in the sensor's "
                    "electronics, a core's loop that follows the sign of the rate, a time base that drifts)",
    "orientation": "a dependence on orientation that the linear calibration, nonlinearity and crossfield do not take "
                   "(a soft-iron part moving with the sensor, a field of the platform)",
    "heading": "a dependence on heading: a field of the platform or the site that turns with it (platform, "
               "gradient with the attitude logged)",
    "field magnitude": "a dependence on the field's size (a non-linear response the nonlinearity term does not take)",
}


def _followed(col: str, follows: list[dict[str, Any]]) -> bool:
    """Whether the residual follows column `col` (where it fails: its correlation ratio over bins of the column, which
    any function of it shows, or the column times the field direction): a band that only holds combinations of the
    column's lines, as a band an octave wide often does by chance, is no evidence of a function of it (a real board
    with an uncoupled servo column logged was advised "a non-linear function of servo_deg", which explained 9 %)."""
    return any(f["observable"] in (col, f"{col} x field direction") and f["strength"] >= FOLLOWS for f in follows)


def _shape_advice(col: str, why: str) -> str:
    """A residual that a logged column's motion makes (its lines' harmonics and sums): a non-linear function of it."""
    return (f"a non-linear function of {col}, which the file logs ({why}): a field that follows {col} through a "
            f"shape no catalogue term has (a distance, a power, a saturation), which discovery's shapes of {col} try; "
            f"an effect of your own on {col} (docs/effects.md) if they do not take it")


def _follows_advice(top: dict[str, Any], carried: "Carried | None" = None,
                    follows: list[dict[str, Any]] | None = None) -> str:
    carried = carried or Carried()
    obs = top["observable"]
    if obs == "frequency":
        made = carried.harmonic(band_hz=top.get("band_hz")) if top.get("band_hz") else None
        if made is not None and _followed(made[0], follows or [top]):
            return _shape_advice(made[0], f"the band {top.get('band', '')} holds {made[1]}")
        if (top.get("turning_share") or 0.0) >= TURNING_SHARE:
            return (f"a misfit at the rates the probe turns ({top.get('band', 'one band')} holds "
                    f"{100 * top['turning_share']:.0f} % of the turning of the field it reads): it follows the "
                    f"direction the probe points, not something turning near it (an effect of the field's direction, "
                    f"as nonlinearity, crossfield and hysteresis are, or a shape the calibration's order cannot take); "
                    f"turn through the same directions at another rate to tell a direction from a rate")
        unfollowed = carried.unfollowed({f["observable"] for f in follows or [top]})
        logged = f" ({unfollowed})" if unfollowed else ""
        return (f"a narrow-band disturbance at {top.get('band', 'one band')} (something turning, vibrating or "
                f"switching at that rate near the probe){logged}: "
                + _either(ask("phase", carried), "add an effect of your own (docs/effects.md)"))
    if obs == "time":
        return _time_advice(None, {}, carried)
    if obs.endswith(" x field direction"):
        col = obs[:-len(" x field direction")]
        return (f"a coupling of {col} seen through the field's direction (an offset or a scale that follows {col}: "
                f"in the scalar channel it shows as {col} times the field direction's components), which no catalogue "
                f"term takes as it is: an effect of your own on {col} (docs/effects.md)")
    return _ADVICE.get(obs, f"a coupling of {obs} (a column of the data) that no catalogue term takes: an effect of "
                            f"your own on that column (docs/effects.md)")


def channels_above(fit: FitResult, heldout_nT: np.ndarray, noise: np.ndarray,
                   where: list[dict[str, Any]] | None = None, *, held_out_only: bool = False) -> list[dict[str, Any]]:
    """The channels whose RMS stands above CHANNEL_FACTOR times their own floor held out and in the fit (held out
    alone: what discovery looks at, which costs nothing where it finds nothing), furthest first (held out), each with
    what its residual follows (where_it_fails, FOLLOWS and up): JSON-ready."""
    out = []
    for c, name in enumerate(fit.channels.names):
        ratio = float(heldout_nT[c] / noise[c]) if noise[c] > 0 else float("inf")
        fitted = float(fit.channels.rms_nT[c] / noise[c]) if noise[c] > 0 else float("inf")
        if not (ratio > CHANNEL_FACTOR and (held_out_only or fitted > CHANNEL_FACTOR)):
            continue
        follows = [{"observable": w["observable"], "strength": w["strength"],
                    **({"band": w["band"]} if w.get("band") else {})}
                   for w in where or [] if w["channel"] == name and w["strength"] >= FOLLOWS][:2]
        out.append({"channel": name, "family": fit.problem.channel_probe(c)[0], "heldout_rms_nT": float(heldout_nT[c]),
                    "rms_nT": float(fit.channels.rms_nT[c]), "floor_nT": float(noise[c]), "ratio": ratio,
                    "follows": follows})
    return sorted(out, key=lambda e: -e["ratio"])


#: at most this many channels are named in the verdict's text (all in --json)
CHANNELS_SAID = 4


def channels_text(above: list[dict[str, Any]]) -> str:
    """'s1.scalar 1.42 x its floor, s2-s1.z 1.39 x (following coil_A) on the held-out blocks'."""
    def one(e: dict[str, Any]) -> str:
        follows = ", ".join(f"{f['observable']}{' ' + f['band'] if f.get('band') else ''} "
                            f"{100 * f['strength']:.0f} %" for f in e["follows"])
        return f"{e['channel']} {e['ratio']:.2f} x its {e['floor_nT']:.2f} nT floor" + (
            f" (following {follows})" if follows else "")
    more = len(above) - CHANNELS_SAID
    return ("left above their own floor on the held-out blocks: " + "; ".join(one(e) for e in above[:CHANNELS_SAID])
            + (f"; and {more} more channel{'s' if more > 1 else ''}" if more > 0 else ""))


def verdict(rms_nT: float, noise_nT: float, best: Any, left: dict[str, Any],
            carried: "Carried | bool", above: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """The verdict in three kinds (plus "at the floor"), JSON-ready; `left` the signature of what the best
    candidate (or the model, without one) leaves; `above` the channels it leaves above their own floor
    (channels_above): "at the floor" and "explained" need none."""
    above = list(above or [])
    if best is None and rms_nT <= FLOOR_FACTOR * noise_nT and not above:
        return {"kind": "at the floor", "effect": None, "rms_nT": rms_nT, "floor_nT": noise_nT,
                "left": None, "advice": None, "channels_above": []}
    after = best.rms_nT if best is not None else rms_nT
    if best is not None and after <= FLOOR_FACTOR * noise_nT and not above:
        kind = "explained"
    elif best is not None:
        kind = "partly explained"
    else:
        kind = "unexplained"
    what, advice = describe({**left, "channels_above": above}, carried)
    return {"kind": kind, "effect": None if best is None else best.effect, "rms_nT": after, "floor_nT": noise_nT,
            "left": None if kind == "explained" else what, "advice": None if kind == "explained" else advice,
            "signature": left, "channels_above": above}
