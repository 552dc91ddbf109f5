"""softc.ray.map on a local Ray: results in order and equal to serial evaluation."""

import numpy as np
import pytest

ray = pytest.importorskip("ray")
import softc  # noqa: E402
import softc.ray  # noqa: E402
from conftest import SCENES, without_timing  # noqa: E402


@pytest.fixture(scope="module")
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def test_map_equals_serial_runs(local_ray, beam):
    params = [{"p0": p} for p in (4e3, 8e3, 12e3, 16e3)]
    results = softc.ray.map(SCENES / "beam.soft", params, steps=120)
    assert len(results) == 4
    for p, r in zip(params, results):
        assert without_timing(r) == without_timing(beam.run(p, steps=120))
    losses = [r["loss"] for r in results]
    assert losses == sorted(losses)  # more pressure, farther from rest


def test_map_with_gradients_equals_loss_and_grad(local_ray, beam):
    params = [{"p0": 6e3}, {"p0": 9e3, "mu": np.full(beam.params["mu"].shape, 25e3)}]
    results = softc.ray.map(SCENES / "beam.soft", params, grad=True, steps=120)
    for p, (loss, grads) in zip(params, results):
        expected_loss, expected = beam.loss_and_grad(p, steps=120)
        assert loss == expected_loss
        assert grads["p0"] == expected["p0"]
        np.testing.assert_array_equal(grads["mu"], expected["mu"])


def test_a_failed_task_raises_its_error(local_ray):
    with pytest.raises(softc.SimulationError, match="outside the bounds"):
        softc.ray.map(SCENES / "beam.soft", [{"p0": 1e3}, {"p0": 90e3}], steps=10)


def test_unknown_options_and_scripts(local_ray):
    with pytest.raises(TypeError, match="unknown options"):
        softc.ray.map(SCENES / "beam.soft", [{}], stepz=3)
    with pytest.raises(FileNotFoundError):
        softc.ray.map(SCENES / "nope.soft", [{}])


def test_a_task_runs_on_the_cpus_ray_reserved_for_it():
    # Issue 31 item 18: a task compiled with softc's default threads, one per core, so one
    # task per core oversubscribed the machine.
    assert softc.ray._task_options({}, 1.0) == {"threads": 1}
    assert softc.ray._task_options({}, 0.5) == {"threads": 1}
    assert softc.ray._task_options({}, 4.0) == {"threads": 4}
    assert softc.ray._task_options({"threads": 2, "precision": "f32"}, 1.0) == {
        "threads": 2,
        "precision": "f32",
    }
