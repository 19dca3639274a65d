"""The outputs of fit, diagnose and a fleet on the repository's recordings and configurations do not change unless a
change means them to (issue 29: the command layer was rebuilt with every output kept bit for bit). The golden files
in tests/golden/ were written by `python tests/e2e/test_outputs_unchanged.py` with the arithmetic of the machine
named in each: on that arithmetic the JSON must be the same bit for bit, on another (other CPU features, another
BLAS) every number within OTHER_ARITHMETIC_REL (rounding, docs/recording.md "Replay equality"), every word the same.
A change that means to move an output rewrites them with that command, and says so in its commit."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
GOLDEN = ROOT / "tests" / "golden"
CASES = {
    "fit-grad1-sim-30s": ["fit", "recordings/grad1-sim-30s.mcap", "--json"],
    "fit-grad1-sim-30s-config": ["fit", "recordings/grad1-sim-30s.mcap", "--config", "configs/sim-gradiometer.toml",
                                 "--json"],
    "fit-grad1-hidden-effect-temperature": ["fit", "recordings/grad1-hidden-effect.mcap", "--effects", "temperature",
                                            "--json"],
    "diagnose-grad3-pump": ["diagnose", "recordings/grad3-pump.mcap", "--json"],
}
#: on another arithmetic (other CPU kernels, another BLAS): rounding, amplified by the fits' conditioning and the
#: candidates' fits stopped after a few iterations, moved numbers by up to 3e-8 relative (AVX-512 off, and AVX2 off
#: too, against this machine's AVX-512 golden files); every number within this, every word the same
OTHER_ARITHMETIC_REL = 1e-6
#: what differs from run to run by design: wall times and memory of a fleet, the date a file was written
VOLATILE = {"wall_s", "seconds", "peak_rss_mb", "created"}


def run(argv: list[str]) -> dict:
    import contextlib
    import io

    from fluxcal.service.wiring.cli import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        assert main(argv, install_signals=False) == 0
    return json.loads(out.getvalue().strip().splitlines()[-1])


def _same(a, b, rel: float, path: str = "") -> list[str]:
    """Where a and b differ: exactly (rel 0) or beyond `rel` for numbers; words always exactly."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = [f"{path}: keys {sorted(set(a) ^ set(b))}"] if set(a) != set(b) else []
        return out + [d for k in a if k in b and k not in VOLATILE for d in _same(a[k], b[k], rel, f"{path}.{k}")]
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: {len(a)} items against {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _same(x, y, rel, f"{path}[{i}]")]
    if isinstance(a, float) and isinstance(b, float) and not isinstance(a, bool):
        ok = a == b or (rel > 0 and math.isclose(a, b, rel_tol=rel, abs_tol=1e-12))
        return [] if ok else [f"{path}: {a!r} against {b!r}"]
    return [] if a == b else [f"{path}: {a!r} against {b!r}"]


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CASES))
def test_the_outputs_are_the_golden_ones(name, monkeypatch):
    from fluxcal.service.io.recordings.arithmetic import arithmetic_differences, machine_arithmetic

    monkeypatch.chdir(ROOT)
    golden = json.loads((GOLDEN / f"{name}.json").read_text())
    got = run(CASES[name])
    same_arithmetic = not arithmetic_differences(golden["arithmetic"], machine_arithmetic())
    diffs = _same(golden["output"], got, 0.0 if same_arithmetic else OTHER_ARITHMETIC_REL)
    how = "bit for bit on the same arithmetic" if same_arithmetic else f"beyond {OTHER_ARITHMETIC_REL:g} relative"
    assert not diffs, (f"{name}: the output moved ({how}); if meant, rewrite tests/golden with "
                       f"python tests/e2e/test_outputs_unchanged.py: " + "; ".join(diffs[:8]))


def write_golden() -> None:
    from fluxcal.service.io.recordings.arithmetic import machine_arithmetic

    GOLDEN.mkdir(exist_ok=True)
    for name, argv in CASES.items():
        doc = {"argv": argv, "arithmetic": machine_arithmetic(), "output": run(argv)}
        (GOLDEN / f"{name}.json").write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")
        print(f"wrote tests/golden/{name}.json", file=sys.stderr)


if __name__ == "__main__":
    import os

    os.environ["OPENBLAS_NUM_THREADS"] = "1"          # as the suite runs (tests/conftest.py), before numpy loads
    os.chdir(ROOT)
    sys.path[:0] = [str(ROOT)]
    write_golden()
