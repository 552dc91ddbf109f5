"""Shared fixtures: the repository's paths, the `softc` command line to compare against, and
compiled scenes (compiled once per test session)."""

import json
import os
import pathlib
import shutil
import subprocess

import pytest

import softc

ROOT = pathlib.Path(__file__).resolve().parents[2]
SCENES = pathlib.Path(__file__).resolve().parent / "scenes"
EXAMPLES = ROOT / "examples"

# Fields of the JSON summary that measure time, not the simulation.
TIMING = {
    "wall_seconds",
    "steps_per_second",
    "forward_seconds",
    "backward_seconds",
    "assembly_seconds",
    "factor_seconds",
}


def softc_bin() -> str:
    path = os.environ.get("SOFTC_BIN") or shutil.which("softc")
    if not path:
        for profile in ("release", "debug"):
            candidate = ROOT / "target" / profile / "softc"
            if candidate.exists():
                return str(candidate)
        pytest.fail("no softc binary: set SOFTC_BIN or run `cargo build --release -p softc`")
    return path


def cli_json(tmp_path, script, *args) -> dict:
    """`softc run SCRIPT ARGS --json FILE`, parsed."""
    out = tmp_path / "cli.json"
    result = subprocess.run(
        [softc_bin(), "run", str(script), *args, "--json", str(out)],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stderr
    return json.loads(out.read_text())


def without_timing(value):
    """A JSON value with its timing fields removed (they differ between any two runs)."""
    if isinstance(value, dict):
        return {k: without_timing(v) for k, v in value.items() if k not in TIMING}
    if isinstance(value, list):
        return [without_timing(v) for v in value]
    return value


@pytest.fixture(scope="session")
def beam():
    return softc.compile(SCENES / "beam.soft")


@pytest.fixture(scope="session")
def static_pressure():
    return softc.compile(EXAMPLES / "pressure_optimization.soft")


@pytest.fixture(scope="session")
def endoscope():
    return softc.compile(EXAMPLES / "python" / "controller_scene.soft")
