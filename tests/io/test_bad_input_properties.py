"""Property tests: whatever bytes a user hands the CSV, config and calibration-file readers, they either
read it or raise the documented error (DataError / ConfigError) — never a traceback of another kind."""

from __future__ import annotations

import json

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fluxcal.drivers.errors import ConfigError, DataError
from fluxcal.service.io.calfile import calibration_from_json
from fluxcal.service.io.recordings.labdata import load_csv
from fluxcal.service.wiring.config import config_from_dict

SETTINGS = settings(max_examples=int(__import__("os").environ.get("FLUXCAL_PROPERTY_EXAMPLES", "150")), deadline=None,
                    derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])

cell = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr), st.integers().map(str),
                 st.text(alphabet="0123456789.-eEnaif x,#\"", max_size=8))
header = st.lists(st.sampled_from(["t", "s1_x", "s1_y", "s1_z", "s2_x", "s2_y", "s2_z", "s1_temp", "ref_total",
                                   "s3_x", "extra", ""]), min_size=0, max_size=8)


@SETTINGS
@given(header=header, rows=st.lists(st.lists(cell, max_size=9), max_size=6), comments=st.lists(st.text(max_size=10),
                                                                                                max_size=2))
def test_csv_reader_reads_or_names_the_problem(tmp_path, header, rows, comments):
    text = "".join(f"#{c}\n" for c in comments if "\n" not in c and "\r" not in c)
    text += ",".join(header) + "\n" + "\n".join(",".join(r) for r in rows) + "\n"
    p = tmp_path / "x.csv"
    p.write_text(text)
    try:
        data = load_csv(p)
    except DataError as e:
        assert str(p) in str(e)
        return
    b = data.block
    # a probe axis may be NaN (saturated or invalid: the fits leave it out and count it), never inf
    assert not np.isinf(b.field_nT).any() and np.all(np.diff(b.t_s) > 0)
    assert all(np.isfinite(v).all() for v in b.extras.values())


@SETTINGS
@given(st.binary(max_size=200))
def test_csv_reader_on_arbitrary_bytes(tmp_path, blob):
    p = tmp_path / "b.csv"
    p.write_bytes(blob)
    try:
        load_csv(p)
    except DataError:
        pass


toml_value = st.recursive(st.one_of(st.booleans(), st.integers(-10**6, 10**6), st.floats(allow_nan=False),
                                    st.text(max_size=6)),
                          lambda c: st.one_of(st.lists(c, max_size=3), st.dictionaries(st.text(max_size=6), c,
                                                                                        max_size=3)),
                          max_leaves=8)
section = st.sampled_from(["unit", "probes", "source", "estimator", "calibration", "zenoh", "mcap", "typo"])
key = st.sampled_from(["name", "n_probes", "lsb_nT", "kind", "forgetting", "total_nT", "mode", "listen", "dir",
                       "position_m", "file", "transport", "bogus"])


@SETTINGS
@given(st.dictionaries(section, st.dictionaries(key, toml_value, max_size=3), max_size=4))
def test_config_loader_accepts_or_names_the_key(raw):
    raw.pop("sim", None)
    raw.setdefault("source", {"kind": "replay", "path": "x.mcap", "rate_hz": 200.0})
    try:
        config_from_dict(raw, "cfg.toml")
    except ConfigError as e:
        assert str(e).startswith("cfg.toml: ")


GOOD = {"format": "fluxcal.calibration", "version": 1, "method": "ellipsoid", "align": None, "total_nT": 50000.0,
        "effects": [], "span": {"t0_s": 0.0, "t1_s": 1.0, "n_samples": 2},
        "probes": [{"name": "s1", "offset_nT": [1.0, 2.0, 3.0], "matrix": [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]],
                    "offset_se_nT": [None, None, None], "matrix_se": [[None] * 3] * 3, "params": {}}]}


@SETTINGS
@given(path=st.lists(st.sampled_from(["probes", 0, "offset_nT", "matrix", 1, "version", "format", "name", "span"]),
                     min_size=1, max_size=3), value=toml_value)
def test_calibration_reader_refuses_damage_clearly(path, value):
    d = json.loads(json.dumps(GOOD))
    node = d
    try:
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = value
    except (KeyError, IndexError, TypeError):
        return
    try:
        cal = calibration_from_json(json.dumps(d), origin="cal.json")
    except DataError as e:
        assert "cal.json" in str(e)
        return
    assert all(np.isfinite(p.matrix).all() and np.isfinite(p.offset_nT).all() for p in cal.probes)


@SETTINGS
@given(st.text(max_size=300))
def test_calibration_reader_on_arbitrary_text(text):
    try:
        calibration_from_json(text, origin="cal.json")
    except DataError as e:
        assert "cal.json" in str(e)
