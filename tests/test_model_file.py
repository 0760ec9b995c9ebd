"""Model files: exact round trips for both bases and every option, atomic writes, clear errors."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np
import pytest

from usdeform.correction import profiles_along_sweep
from usdeform.errors import FileFormatError, InputError
from usdeform.io import ModelFile, SampledProfiles, load_model, save_model
from usdeform.io.model_file import FORMAT_NAME, FORMAT_VERSION
from usdeform.regression import BSplineDisplacementModel, Normalization, QuadraticDisplacementModel, StiffnessProfile

NORMALIZATION = Normalization(255.0, 127.0, 20.0, 7.25, 3.1, 12.5)
PROFILES = (StiffnessProfile(0.031, 2.2, 0.01), StiffnessProfile(0.0, 1.4, -0.2), StiffnessProfile(0.11, 0.9, 0.0))


def awkward_coefficients(shape: tuple[int, ...]) -> np.ndarray:
    """Random coefficients plus values whose text is easy to get wrong: -0.0, subnormal, huge, 0.1."""
    values = np.random.default_rng(7).normal(size=shape) * 10.0 ** np.random.default_rng(8).integers(-12, 12, shape)
    values.flat[:4] = [-0.0, 5e-324, 1.7976931348623157e308, 0.1]
    return values


def assert_same_model(loaded: ModelFile, model, sampled: SampledProfiles | None) -> None:
    assert type(loaded.model) is type(model)
    assert np.array_equal(loaded.model.coefficients, model.coefficients)
    assert np.array_equal(np.signbit(loaded.model.coefficients), np.signbit(model.coefficients))
    assert loaded.model.normalization == model.normalization
    assert (loaded.model.n_intervals, loaded.model.coupling, loaded.model.integration, loaded.model.frame_shape) == (
        model.n_intervals,
        model.coupling,
        model.integration,
        model.frame_shape,
    )
    if sampled is None:
        assert loaded.sampled is None
    else:
        assert np.array_equal(loaded.sampled.positions_mm, sampled.positions_mm)
        assert loaded.sampled.positions_mm.shape == sampled.positions_mm.shape
        assert loaded.sampled.profiles == sampled.profiles


@pytest.mark.parametrize("coupling", ["stiffness", "force"])
@pytest.mark.parametrize("integration", ["force", "displacement"])
@pytest.mark.parametrize("basis", ["quadratic", "bspline"])
def test_round_trip_is_exact_for_both_bases_and_every_option(
    tmp_path: Path, basis: str, coupling: str, integration: str
) -> None:
    if basis == "quadratic":
        model = QuadraticDisplacementModel(awkward_coefficients((2, 10)), NORMALIZATION, 17, coupling, integration)
        sampled = SampledProfiles(np.array([3.5, 21.0, 40.125]), PROFILES)  # along the sweep
    else:
        model = BSplineDisplacementModel(awkward_coefficients((2, 3, 5, 7)), NORMALIZATION, 64, coupling, integration)
        sampled = SampledProfiles(
            np.array([[550.0, -25.0, 118.52759], [550.0, 5.0, 117.9], [551.0, 30.0, 0.1]]), PROFILES
        )  # base frame
    path = tmp_path / "model.json"
    save_model(path, model, sampled, {"loss": 0.0123, "solver": "exact", "smoothness": 1e-5})
    loaded = load_model(path)
    assert_same_model(loaded, model, sampled)
    assert loaded.provenance["loss"] == 0.0123 and loaded.provenance["smoothness"] == 1e-5
    assert loaded.provenance["usdeform_version"]


def test_the_file_is_versioned_readable_json(tmp_path: Path) -> None:
    model = BSplineDisplacementModel(awkward_coefficients((2, 3, 4, 6)), NORMALIZATION)
    save_model(tmp_path / "model.json", model)
    text = (tmp_path / "model.json").read_text()
    document = json.loads(text)
    assert (document["format"], document["version"]) == (FORMAT_NAME, FORMAT_VERSION)
    assert document["basis"] == {"name": "bspline", "n_y": 4, "n_x": 6}
    assert document["normalization"]["h_scale"] == 7.25
    assert "sampled_positions" not in document
    assert text.count("\n") < model.coefficients.size  # rows of numbers stay on one line
    assert_same_model(load_model(tmp_path / "model.json"), model, None)


def test_the_frame_shape_is_stored_and_version_1_files_migrate(tmp_path: Path) -> None:
    normalization = Normalization.for_frames(96, 200, 20.0, 7.25, 3.1, 12.5)
    model = QuadraticDisplacementModel(awkward_coefficients((2, 10)), normalization, frame_shape=(96, 200))
    save_model(tmp_path / "model.json", model)
    document = json.loads((tmp_path / "model.json").read_text())
    assert document["frame_shape"] == [96, 200]
    assert load_model(tmp_path / "model.json").model.frame_shape == (96, 200)
    # A version-1 file (written before the frame shape was stored) takes it from the normalisation.
    document["version"] = 1
    del document["frame_shape"]
    (tmp_path / "old.json").write_text(json.dumps(document))
    migrated = load_model(tmp_path / "old.json").model
    assert migrated.frame_shape == normalization.frame_shape == (96, 200)
    assert np.array_equal(migrated.coefficients, model.coefficients)


def test_a_model_whose_fields_disagree_is_not_written(tmp_path: Path) -> None:
    """What load_model refuses (issue 43) is refused before writing: scales of another frame shape, and a
    sampled stiffness profile that falls."""
    mismatched = QuadraticDisplacementModel(awkward_coefficients((2, 10)), NORMALIZATION, frame_shape=(96, 200))
    with pytest.raises(InputError, match=r"model: normalization\.x_scale: 255 disagrees with the frame shape 96 x 200"):
        save_model(tmp_path / "model.json", mismatched)
    falling = SampledProfiles(np.array([[0.0, 0.0, 0.0], [0.0, 9.0, 0.0]]), (PROFILES[0], StiffnessProfile(0.1, -1, 0)))
    model = QuadraticDisplacementModel(awkward_coefficients((2, 10)), NORMALIZATION)
    with pytest.raises(InputError, match=r"sampled_positions\[1\]\.profile: .* does not rise over .* 0-20 N"):
        save_model(tmp_path / "model.json", model, falling)
    assert not list(tmp_path.iterdir())


def test_models_pickle_with_their_frame_shape() -> None:
    model = BSplineDisplacementModel(
        awkward_coefficients((2, 3, 4, 5)), NORMALIZATION, 9, "force", frame_shape=(40, 50)
    )
    copy = pickle.loads(pickle.dumps(model))
    assert type(copy) is BSplineDisplacementModel and copy.frame_shape == (40, 50) and copy.coupling == "force"
    assert np.array_equal(copy.displacement(3.0, PROFILES[0], (4, 5)), model.displacement(3.0, PROFILES[0], (4, 5)))


def test_sampled_profiles_propagate_with_the_inverse_distance_weights() -> None:
    sampled = SampledProfiles(np.array([[0.0, 0.0, 0.0], [0.0, 30.0, 0.0], [0.0, 60.0, 5.0]]), PROFILES)
    frames = np.array([[0.0, 30.0, 0.0], [0.0, 12.0, 1.0]])
    assert np.array_equal(sampled.along(frames), profiles_along_sweep(frames, sampled.positions_mm, PROFILES))
    assert tuple(sampled.along(frames)[0]) == PROFILES[1].as_tuple()
    with pytest.raises(InputError, match="profiles"):
        SampledProfiles(np.zeros((2, 3)), PROFILES)


def test_a_failed_save_leaves_the_old_file(tmp_path: Path) -> None:
    path = tmp_path / "model.json"
    model = QuadraticDisplacementModel(awkward_coefficients((2, 10)), NORMALIZATION)
    save_model(path, model)
    before = path.read_bytes()
    with pytest.raises(InputError, match="provenance"):
        save_model(path, model, provenance={"loss": float("nan")})
    with pytest.raises(InputError, match="provenance"):
        save_model(path, model, provenance={"when": object()})
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["model.json"]


def _write_document(path: Path, change) -> Path:
    model = BSplineDisplacementModel(awkward_coefficients((2, 3, 4, 5)), NORMALIZATION)
    save_model(path, model, SampledProfiles(np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]), PROFILES[:2]))
    document = json.loads(path.read_text())
    change(document)
    path.write_text(json.dumps(document))
    return path


def _set(*keys_and_value):
    *keys, value = keys_and_value

    def change(document: dict) -> None:
        for key in keys[:-1]:
            document = document[key]
        document[keys[-1]] = value

    return change


def _delete(*keys):
    def change(document: dict) -> None:
        for key in keys[:-1]:
            document = document[key]
        del document[keys[-1]]

    return change


@pytest.mark.parametrize(
    "change, field",
    [
        (_delete("coefficients"), "coefficients: missing field"),
        (_delete("normalization", "axial_scale"), "normalization.axial_scale: missing field"),
        (_delete("sampled_positions", 1, "profile", "c2"), r"sampled_positions\[1\].profile.c2: missing field"),
        (_delete("format"), "format: missing field"),
        (_set("format", "something-else"), "format: expected one of 'usdeform-deformation-model'"),
        (_set("version", 3), "version: this usdeform reads versions 1, 2, got 3"),
        (_delete("frame_shape"), "frame_shape: missing field"),
        (_set("frame_shape", [64]), r"frame_shape: expected \[rows, cols\], got \[64\]"),
        (_set("frame_shape", 1, 0), r"frame_shape\[1\]: expected an integer from 1 to 65536, got 0"),
        (_set("basis", "name", "thin-plate"), "basis.name: expected one of 'quadratic', 'bspline'"),
        (
            _set("basis", {"name": "quadratic"}),
            r"coefficients: expected shape \(2, 10\) for the basis; coefficients\[0\] has 3 items",
        ),
        (
            _set("basis", "n_x", 6),
            r"coefficients: expected shape \(2, 3, 4, 6\) for the basis; coefficients\[0\]\[0\]\[0\] has 5 items",
        ),
        (_set("basis", "n_y", 2), "basis.n_y: expected an integer from 4 to 4096"),
        (_set("coefficients", 1, 2, 3, 4, float("nan")), r"coefficients\[1\]\[2\]\[3\]\[4\]: non-finite number"),
        (_set("coefficients", 0, 0, 0, 0, "1.5"), r"coefficients\[0\]\[0\]\[0\]\[0\]: expected a number"),
        (_set("normalization", "x_scale", float("inf")), "normalization.x_scale: non-finite number"),
        (_set("normalization", "x_scale", -1.0), "normalization.x_scale: -1 disagrees with frame_shape 128 x 256"),
        (
            _set("normalization", "force_scale", -1.0),
            "Normalization: x_scale, y_scale, force_scale, h_scale must be positive",
        ),
        (_set("n_intervals", 2.5), "n_intervals: expected an integer from 1 to 1000000"),
        (_set("coupling", "pressure"), "coupling: expected one of"),
        (_set("integration", "time"), "integration: expected one of"),
        (
            _set("sampled_positions", 1, "position_mm", [4.0, 5.0]),
            r"sampled_positions\[1\].position_mm: expected shape \(3,\) like sampled_positions\[0\]; "
            r"sampled_positions\[1\].position_mm has 2 items",
        ),
        (_set("sampled_positions", 0, "profile", "c1", None), r"sampled_positions\[0\].profile.c1: expected a number"),
        (_set("sampled_positions", []), "sampled_positions: expected a non-empty list"),
        (_set("solver", "exact"), "solver: unknown field"),
        (_set("provenance", [1, 2]), "provenance: expected a JSON object"),
    ],
)
def test_malformed_files_name_the_file_and_the_field(tmp_path: Path, change, field: str) -> None:
    path = _write_document(tmp_path / "model.json", change)
    with pytest.raises(FileFormatError, match=field) as raised:
        load_model(path)
    assert str(raised.value).startswith(f"{path}: ")


@pytest.mark.parametrize(
    "text, message", [(b'{"format": ', "not JSON"), (b"[1, 2]", "expected a JSON object"), (b"\xff\xfe{}", "not UTF-8")]
)
def test_files_that_are_not_model_files(tmp_path: Path, text: bytes, message: str) -> None:
    path = tmp_path / "model.json"
    path.write_bytes(text)
    with pytest.raises(FileFormatError, match=message):
        load_model(path)


def test_unknown_model_types_are_refused(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="model: expected"):
        save_model(tmp_path / "model.json", object())  # type: ignore[arg-type]
    assert not (tmp_path / "model.json").exists()
