"""Where the tests find the public recordings of real magnetometers and the real flight logs: never in the
repository (their licences do not all allow it). A file is looked for in ../shared/real-data beside the checkout
(where CI has it), then in the folder the environment variable FLUXCAL_REAL_DATA names; a test whose file is in
neither skips, naming both places and where the file comes from.

    from real_data import real, needs_real
    path = real("qmc5883l_suarez.csv")               # the file, or the test skips (the reason says why)
    @needs_real("px4_pyulog_sample.ulg")             # a test (or parametrized test) that needs these files
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ENV = "FLUXCAL_REAL_DATA"
SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "real-data"

_PYULOG = "github PX4/pyulog @3cf17793f14709713ab297d3743314c658874068"
_PYMAVLINK = "github ArduPilot/pymavlink @b4c7ca298cfac46aa841994d5d3288143e2fa7e5"
_ERLE = "github erlerobot/logs @3f7d4a0d17f2485f7fa5cb7124fc2a5b13d6c688"
_FUSION = "github sunsided/sensor-fusion @f16045a, data/set-2/"
_CSV = "converted to fluxcal's CSV (the file's header says how) from "
_EVO = "github MichaelGrupp/evo @26d0953d4da0f0cb56f90ba6269a15e72f69d3ad"
_ROSBAG2 = "github ros2/rosbag2 @25304dd36e51cc0fbccf148fded2dd4ba5ccba35"
#: public logs fetched for the new-user trial of issue 37 (not in ../shared/real-data: put them in $FLUXCAL_REAL_DATA
#: under these names; a rosbag2 directory as a folder holding its metadata.yaml and .db3)
FETCHED = {
    "px4_pyulog_sample_appended_multiple.ulg": f"{_PYULOG}, test/sample_appended_multiple.ulg (BSD-3-Clause)",
    "px4_pyulog_sample_logging_tagged.ulg": f"{_PYULOG}, test/sample_logging_tagged_and_default_params.ulg "
                                            "(BSD-3-Clause)",
    "px4_pyulog_sample_px4_events.ulg": f"{_PYULOG}, test/sample_px4_events.ulg (BSD-3-Clause)",
    "ardupilot_erlerobot_erlebrain_22.BIN": f"{_ERLE}, erlebrain/APM/22.BIN (no licence stated)",
    "ardupilot_erlerobot_erlebrain_24.BIN": f"{_ERLE}, erlebrain/APM/24.BIN (no licence stated)",
    "ardupilot_erlerobot_erlebrain_7.BIN": f"{_ERLE}, erlebrain/APM/7.BIN (no licence stated)",
    "ardupilot_erlerobot_copter_218.BIN": f"{_ERLE}, pxf/copter/5-12-2014/218.BIN (no licence stated; an older log: "
                                          "GPS TimeMS is the time of week)",
    "ardupilot_erlerobot_copter_gps_issues1.BIN": f"{_ERLE}, pxf/copter/6-11-2014/GPS_issues1.BIN (no licence "
                                                  "stated; its compass reads 0)",
    "ardupilot_erlerobot_plane_329.BIN": f"{_ERLE}, pxf/plane/4-12-2014/329.BIN (no licence stated; no MAG)",
    "ardupilot_erlerobot_rover_61.BIN": f"{_ERLE}, pxf/rover/25-8-2014/61.BIN (no licence stated; no MAG)",
    "ros2_evo_nav2_turtlebot.mcap": f"{_EVO}, test/data/nav2_turtlebot.mcap (GPL-3.0)",
    "ros2_evo_tf_example": f"{_EVO}, test/data/tf_example/ (metadata.yaml, tf_example.db3; GPL-3.0)",
    "ros2_rosbag2_talker": f"{_ROSBAG2}, rosbag2_py/test/resources/sqlite3/talker/ (metadata.yaml, talker.db3; "
                           "Apache-2.0)",
    "ros2_rosbag2_cdr_test.mcap": f"{_ROSBAG2}, rosbag2_tests/resources/mcap/cdr_test/cdr_test_0.mcap (Apache-2.0)",
}

#: where each file comes from: repository, commit, path in it (and licence where it has one)
SOURCES = {
    "px4_sample_log_small.ulg": f"{_PYULOG}, test/sample_log_small.ulg (BSD-3-Clause)",
    "px4_pyulog_sample.ulg": f"{_PYULOG}, test/sample.ulg (BSD-3-Clause)",
    "ardupilot_pymavlink_test.BIN": f"{_PYMAVLINK}, tests/test.BIN (LGPL-3.0)",
    "ardupilot_erlerobot_pxf_copter.BIN": f"{_ERLE}, pxf/copter/PXFv2.0b+Rpi.BIN (no licence stated)",
    "ardupilot_erlerobot_erlebrain3.BIN": f"{_ERLE}, pxf/copter/Erle-Brain3.BIN (no licence stated)",
    "qmc5883l_suarez.csv": f"{_CSV}github tomisuarez2/MagnetometerCalibration @9590433, "
                           "calibration data/filtered_raw_data.csv",
    "imu_freeimucal.csv": f"{_CSV}github uutzinger/freeIMUCal @b15b2d3, mag_data.txt",
    "hmc5883l_nliaudat.csv": f"{_CSV}github nliaudat/magnetometer_calibration @2f65d06, mag_out_sample.txt",
    "hmc5883l_sensorfusion_sphere.csv": f"{_CSV}{_FUSION}full-sphere/*.mat (EUPL-1.2)",
    **{f"hmc5883l_sensorfusion_turn_{a}.csv": f"{_CSV}{_FUSION}rotate-ccw-around-{a}-pointing-{d}/*.mat (EUPL-1.2)"
       for a, d in (("x", "forward"), ("y", "left"), ("z", "up"))},
    "qmc5883l_suarez.published.json": "the calibration published in github tomisuarez2/MagnetometerCalibration "
                                      "@9590433",
    "imu_freeimucal.published.json": "the calibration published in github uutzinger/freeIMUCal @b15b2d3",
    "hmc5883l_nliaudat.published.json": "the calibration published in github nliaudat/magnetometer_calibration "
                                        "@2f65d06",
    **FETCHED,
}


def places() -> list[Path]:
    """The folders looked in, in order."""
    extra = os.environ.get(ENV, "").strip()
    return [SHARED] + ([Path(extra).expanduser()] if extra else [])


def find(name: str) -> Path | None:
    """The first of places() that holds the file (or rosbag2 folder) `name`, or None."""
    return next((p / name for p in places() if (p / name).is_file() or (p / name / "metadata.yaml").is_file()),
                None)


def absent(name: str) -> str:
    """Why a test of `name` skips: where it was looked for, and where the file comes from."""
    env = os.environ.get(ENV, "").strip()
    where = f"{SHARED}, nor in ${ENV}" + (f" ({env})" if env else " (not set)")
    return (f"{name} is neither in {where}: public data, never in the repository; it comes from "
            f"{SOURCES.get(name, 'see ../shared/real-data/README.md')}")


def real(name: str) -> Path:
    """The real-data file `name`; the calling test skips where it is absent (absent(name) says why)."""
    path = find(name)
    if path is None:
        pytest.skip(absent(name))
    return path


def needs_real(*names: str) -> pytest.MarkDecorator:
    """Skip the test where any of these files is absent (the first one missing named in the reason)."""
    missing = [n for n in names if find(n) is None]
    return pytest.mark.skipif(bool(missing), reason=absent(missing[0]) if missing else "")


#: files of ../shared/real-data whose stated unit puts the sensor in a field no Earth has, and the factor a test takes
#: them in: fit and diagnose refuse such data (a total field outside 20,000-70,000 nT), so the tests that run them on
#: these boards read real_nT(name). qmc5883l_suarez: at the 8.333 nT per count of the ±2 G range its source states,
#: the board reads 8,946 nT about its fitted centre; at the QMC5883L's 8 G range (3,000 counts per gauss, 4 times the
#: 2 G range's 12,000) 35,800 nT, an Earth's field. An assumption about the source, said wherever it is used.
UNIT_MENDS = {"qmc5883l_suarez": 4.0}
_MENDED: dict[str, Path] = {}


def mend(name: str) -> float:
    """The factor real_nT takes the file `name` (with or without its suffix) in; 1 for the others."""
    return UNIT_MENDS.get(name.split(".")[0], 1.0)


def real_nT(name: str) -> Path:
    """real(name), or for a file of UNIT_MENDS a copy (once per process, in the temporary folder) with its probe
    columns times the factor and a comment saying so."""
    import atexit
    import shutil
    import tempfile

    path = real(name)
    factor = mend(name)
    if factor == 1.0:
        return path
    if name not in _MENDED:
        folder = Path(tempfile.mkdtemp(prefix="fluxcal-real-nT-"))
        atexit.register(shutil.rmtree, folder, True)
        lines = path.read_text().splitlines()
        head = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
        cols = lines[head].split(",")
        probe = [i for i, c in enumerate(cols) if c.startswith("s") and c.endswith(("_x", "_y", "_z"))]
        out = lines[:head] + [f"# tests/real_data.py: probe columns x {factor:g} (UNIT_MENDS)", lines[head]]
        for ln in lines[head + 1:]:
            v = ln.split(",")
            for i in probe:
                v[i] = repr(float(v[i]) * factor)
            out.append(",".join(v))
        (folder / name).write_text("\n".join(out) + "\n")
        _MENDED[name] = folder / name
    return _MENDED[name]
