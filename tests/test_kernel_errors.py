"""Bad input to the kernels gives a clear usdeform error naming the argument; panics never escape."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator

import numpy as np
import pytest

from kernel_inputs import random_model, random_tracking_pair
from usdeform import _core
from usdeform.correction import correct_frames
from usdeform.errors import InputError, InternalError, MemoryLimitError, UsdeformError
from usdeform.regression import Normalization, QuadraticDisplacementModel, StiffnessProfile
from usdeform.volume import Compounder, VoxelGrid, compound_frames

ROWS, COLS = 12, 10
PROFILE = StiffnessProfile(0.1, 2.0, 0.0)


@pytest.fixture
def model() -> QuadraticDisplacementModel:
    return random_model(np.random.default_rng(0), ROWS, COLS)


@pytest.fixture
def grid() -> VoxelGrid:
    return VoxelGrid((8, 8, 8), np.eye(4))


def frames(n: int = 2, dtype: type = np.uint8) -> np.ndarray:
    return np.zeros((n, ROWS, COLS), dtype=dtype)


def test_errors_are_value_errors_of_one_hierarchy() -> None:
    assert issubclass(InputError, ValueError) and issubclass(InputError, UsdeformError)
    assert issubclass(MemoryLimitError, InputError)
    assert issubclass(InternalError, UsdeformError) and not issubclass(InternalError, ValueError)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (
            lambda m: correct_frames(frames(dtype=np.float64), [1.0, 2.0], PROFILE, m),
            "frames: expected uint8 or float32",
        ),
        (lambda m: correct_frames(frames(), [1.0], PROFILE, m), "forces: expected 2 values"),
        (lambda m: correct_frames(frames(), [1.0, np.nan], PROFILE, m), "forces: non-finite value"),
        (lambda m: correct_frames(frames(), [1.0, 2.0], np.ones((3, 3)), m), "profiles: expected shape (2, 3)"),
        (lambda m: correct_frames(np.zeros((0, ROWS, COLS), np.uint8), [], PROFILE, m), "frames: expected a non-empty"),
        (
            lambda m: correct_frames(frames(), [1.0, 2.0], PROFILE, m, fill=300),
            "fill: expected a finite value in [0, 255]",
        ),
        (lambda m: correct_frames(frames(), [1.0, 2.0], PROFILE, m, threads=0), "threads: expected 1 to 1024"),
        (lambda m: correct_frames(frames(), [1.0, 2.0], PROFILE, m, threads=10**6), "threads: expected 1 to 1024"),
        (lambda m: correct_frames(frames(), [0.5, 2.0], StiffnessProfile(-1.0, 2.0, 0.0), m), "forces: frame 1"),
        (lambda m: correct_frames(frames(), [1.0, 5.0], StiffnessProfile(0.0, -2.0, 0.0), m), "forces: frame 0"),
    ],
)
def test_bad_correction_input_names_the_argument(model: QuadraticDisplacementModel, call, message: str) -> None:
    with pytest.raises(InputError) as error:
        call(model)
    assert message in str(error.value)


MODEL_ARGUMENTS = {
    "basis": "quadratic",
    "coefficients": np.zeros((2, 10)),
    "normalization": np.ones(6),
    "n_intervals": 8,
    "coupling": "stiffness",
    "integration": "force",
    "frame_shape": (ROWS, COLS),
}


def core_model(**arguments: object) -> _core.Model:
    call = {**MODEL_ARGUMENTS, **arguments}
    return _core.Model(call.pop("basis"), call.pop("coefficients"), call.pop("normalization"), **call)


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ({"coefficients": np.zeros((2, 9))}, "coefficients: expected shape (2, 10) for the quadratic basis"),
        ({"coefficients": np.zeros((2, 10), np.float32)}, "coefficients: expected dtype float64, got float32"),
        ({"coefficients": np.zeros((10, 2)).T}, "coefficients: expected a C-contiguous array"),
        ({"coefficients": [[0.0] * 10] * 2}, "coefficients: expected a numpy array (2, 10) for the quadratic basis"),
        ({"basis": "bspline"}, "coefficients: expected shape (2, 3, n_y, n_x) with n_y, n_x >= 4"),
        ({"basis": "cubic"}, "basis: expected 'quadratic' or 'bspline', got \"cubic\""),
        ({"normalization": np.array([1.0, 1.0, 0.0, 1.0, 1.0, 1.0])}, "normalization: the divisors"),
        ({"normalization": np.ones(5)}, "normalization: expected shape (6,)"),
        ({"n_intervals": 0}, "n_intervals: expected 1 to 1000000, got 0"),
        ({"n_intervals": 10**7}, "n_intervals: expected 1 to 1000000"),
        ({"coupling": "tissue"}, "coupling: expected 'stiffness' or 'force'"),
        ({"integration": "time"}, "integration: expected 'force' or 'displacement'"),
        ({"frame_shape": (0, COLS)}, "frame_shape: expected a non-empty (rows, cols)"),
    ],
)
def test_bad_model_arguments_name_the_argument(arguments: dict, message: str) -> None:
    with pytest.raises(InputError) as error:
        core_model(**arguments)
    assert message in str(error.value)


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ({"frames": np.zeros((ROWS, COLS), np.uint8)}, "frames: expected shape (n_frames, rows, cols)"),
        (
            {"frames": np.zeros((1, ROWS, COLS), np.int16)},
            "frames: expected an array (n_frames, rows, cols) of uint8 or float32, got int16",
        ),
        (
            {"frames": np.zeros((1, ROWS + 1, COLS), np.uint8)},
            f"frames: expected frames of the model's frame shape {ROWS} x {COLS} (rows x cols), "
            f"got {ROWS + 1} x {COLS}",
        ),
    ],
)
def test_bad_core_arguments_name_the_argument(arguments: dict, message: str) -> None:
    call = {
        "frames": np.zeros((1, ROWS, COLS), np.uint8),
        "forces": np.ones(1),
        "profiles": np.array([[0.0, 1.0, 0.0]]),
    }
    call.update(arguments)
    with pytest.raises(InputError) as error:
        _core.warp_frames(call["frames"], call["forces"], call["profiles"], core_model())
    assert message in str(error.value)


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (
            {"displacements": np.zeros((1, 2, ROWS, COLS + 1))},
            f"displacements: expected shape (n_frames, 2, rows, cols) of float64, the frames' own, "
            f"got [1, 2, {ROWS}, {COLS + 1}]",
        ),
        (
            {"displacements": np.zeros((1, 2, ROWS, COLS), np.float32)},
            "displacements: expected dtype float64, got float32",
        ),
        ({"displacements": np.zeros((1, 2, ROWS, COLS))[..., ::-1]}, "displacements: expected a C-contiguous array"),
        ({"fill": 300.0}, "fill: expected a finite value in [0, 255] for uint8 frames, got 300"),
        ({"threads": 0}, "threads: expected 1 to 1024"),
    ],
)
def test_bad_field_warp_arguments_name_the_argument(arguments: dict, message: str) -> None:
    call: dict = {"frames": np.zeros((1, ROWS, COLS), np.uint8), "displacements": np.zeros((1, 2, ROWS, COLS))}
    call.update(arguments)
    with pytest.raises(InputError) as error:
        _core.warp_by_field(**call)
    assert message in str(error.value)


def test_frames_of_another_shape_than_the_model_are_refused(model: QuadraticDisplacementModel, grid: VoxelGrid) -> None:
    assert model.frame_shape == (ROWS, COLS)
    wrong = np.zeros((2, 2 * ROWS, 2 * COLS), np.uint8)
    expected = rf"frames: expected frames of the model's frame shape {ROWS} x {COLS} \(rows x cols\), got {2 * ROWS} x"
    with pytest.raises(InputError, match=expected):
        correct_frames(wrong, [1.0, 2.0], PROFILE, model)
    compounder = Compounder(grid)
    with pytest.raises(InputError, match=expected):
        compounder.add_corrected_frames(wrong, np.stack([np.eye(4)] * 2), [1.0, 2.0], PROFILE, model)
    assert compounder.frames_inserted == 0


def test_normalization_and_model_validate_on_construction() -> None:
    with pytest.raises(InputError, match=r"h_scale must be positive|must be positive"):
        Normalization(1.0, 1.0, 1.0, 0.0)
    with pytest.raises(InputError, match=r"coefficients: expected shape \(2, 10\)"):
        QuadraticDisplacementModel(np.zeros((3, 10)), Normalization(1, 1, 1, 1))
    with pytest.raises(InputError, match="coefficients: contain non-finite"):
        QuadraticDisplacementModel(np.full((2, 10), np.inf), Normalization(1, 1, 1, 1))


def test_grid_over_the_memory_limit_is_refused_before_allocating(grid: VoxelGrid) -> None:
    huge = VoxelGrid((4096, 4096, 4096), np.eye(4))  # 1 TiB: allocating it would fail outright
    with pytest.raises(MemoryLimitError, match="raise max_bytes"):
        Compounder(huge)
    small_limit = grid.shape[0] * grid.shape[1] * grid.shape[2] * 16 - 1
    with pytest.raises(MemoryLimitError):
        Compounder(grid, max_bytes=small_limit)
    Compounder(grid, max_bytes=small_limit + 1)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"interpolation": "cubic"}, "interpolation: expected 'nearest' or 'linear'"),
        ({"compounding": "median"}, "compounding: expected 'mean', 'max' or 'latest'"),
    ],
)
def test_bad_compounding_options(grid: VoxelGrid, kwargs: dict, message: str) -> None:
    with pytest.raises(InputError, match=message):
        Compounder(grid, **kwargs)


def test_bad_poses_name_the_frame(grid: VoxelGrid) -> None:
    poses = np.stack([np.eye(4)] * 3)
    poses[2, 0, 1] = np.nan
    with pytest.raises(InputError, match="image_to_world: frame 2"):
        compound_frames(frames(3), poses, grid)
    with pytest.raises(InputError, match=r"image_to_world: expected shape \(3, 4, 4\)"):
        compound_frames(frames(3), poses[:2], grid)
    poses = np.stack([np.eye(4)] * 3)
    poses[1, 3] = [0, 0, 1, 1]
    with pytest.raises(InputError, match="image_to_world: frame 1: the last row"):
        compound_frames(frames(3), poses, grid)


def test_failed_insert_leaves_the_volume_untouched(grid: VoxelGrid) -> None:
    compounder = Compounder(grid)
    compounder.add_frames(np.full((1, ROWS, COLS), 7, np.uint8), np.eye(4)[np.newaxis])
    before = compounder.volume()
    poses = np.stack([np.eye(4)] * 2)
    poses[1, 0, 0] = np.inf
    with pytest.raises(InputError):
        compounder.add_frames(frames(2), poses)
    after = compounder.volume()
    assert np.array_equal(before.image, after.image) and np.array_equal(before.weight, after.weight)
    assert compounder.frames_inserted == 1


def test_bad_grid() -> None:
    with pytest.raises(InputError, match="index_to_world: the 3x3 part is singular"):
        VoxelGrid((2, 2, 2), np.diag([1.0, 0.0, 1.0, 1.0]))
    with pytest.raises(InputError, match="shape: expected three positive voxel counts"):
        VoxelGrid((2, 0, 2), np.eye(4))


def test_a_panic_in_the_core_becomes_internal_error() -> None:
    with pytest.raises(InternalError, match="deliberate panic"):
        _core._panic_for_tests()
    # The interpreter and the module keep working afterwards.
    assert _core.force_integrals(1.0, (0.0, 1.0, 0.0), np.ones(6), 4)[0] == 1.0


@pytest.mark.parametrize("shape", [(10**6, 10**6), (2**40, 2**40)])
def test_an_impossible_field_is_a_memory_error_not_an_abort(model: QuadraticDisplacementModel, shape) -> None:
    with pytest.raises(MemoryLimitError, match="rows, cols: the output needs"):
        model.displacement(1.0, PROFILE, shape)


@contextlib.contextmanager
def _ctrl_c_once_the_kernel_runs() -> Iterator[threading.Event]:
    """Yield an event to set just before calling a kernel; Ctrl-C (SIGINT) is then sent from another thread
    as soon as that thread can run, which is when the kernel releases the GIL: with a switch interval longer
    than the test, the calling thread never yields it in between. No timer, so the machine's load does not
    decide whether the signal lands before, inside or after the kernel (issue 43)."""
    started = threading.Event()

    def interrupt() -> None:
        started.wait()
        os.kill(os.getpid(), signal.SIGINT)

    interval = sys.getswitchinterval()
    sender = threading.Thread(target=interrupt)
    sys.setswitchinterval(1000.0)
    try:
        sender.start()
        yield started
    finally:
        started.set()  # a kernel that failed to start still lets the sender finish
        sys.setswitchinterval(interval)
        sender.join()


@pytest.mark.parametrize("fused", [False, True])
def test_ctrl_c_interrupts_a_long_kernel(fused: bool) -> None:
    """Signals are checked between chunks of frames: Ctrl-C raises KeyboardInterrupt mid-run. The sender
    runs only while a kernel has released the GIL, but when the system schedules it is the system's choice
    (on a busy machine, after a whole call): the kernel is called again until the signal lands, up to
    max_calls times, so the verdict does not depend on the machine's load."""
    rows = cols = 128
    n_frames, max_calls = 6000, 50
    rng = np.random.default_rng(1)
    model = random_model(rng, rows, cols)
    stack = np.zeros((n_frames, rows, cols), np.uint8)
    compounder = Compounder(VoxelGrid((64, 64, 64), np.eye(4)))
    poses = np.repeat(np.eye(4)[np.newaxis], n_frames, axis=0)
    with pytest.raises(KeyboardInterrupt), _ctrl_c_once_the_kernel_runs() as started:
        started.set()
        for _ in range(max_calls):
            if fused:
                compounder.add_corrected_frames(stack, poses, 1.0, PROFILE, model, threads=1)
            else:
                correct_frames(stack, 1.0, PROFILE, model, threads=1)
    if fused:
        assert compounder.frames_inserted < max_calls * n_frames


def test_a_compounder_shared_between_threads_never_raises_a_borrow_error(grid: VoxelGrid) -> None:
    """Calls racing on one compounder either run or fail with a clear UsdeformError."""
    compounder = Compounder(grid)
    stack = np.ones((400, ROWS, COLS), np.uint8)
    poses = np.repeat(np.eye(4)[np.newaxis], len(stack), axis=0)
    outcomes: list[BaseException | None] = []

    def insert() -> None:
        try:
            for _ in range(20):
                compounder.add_frames(stack, poses, threads=1)
                compounder.volume()
            outcomes.append(None)
        except BaseException as error:
            outcomes.append(error)

    workers = [threading.Thread(target=insert) for _ in range(4)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    errors = [outcome for outcome in outcomes if outcome is not None]
    assert len(outcomes) == 4
    for error in errors:
        assert isinstance(error, UsdeformError) and not isinstance(error, InternalError), repr(error)
        assert "another thread is using this compounder" in str(error)
    assert compounder.frames_inserted % len(stack) == 0


def _pattern(indptr: list[int], indices: list[int]) -> _core.SymmetricSolver:
    return _core.SymmetricSolver(np.array(indptr, np.int64), np.array(indices, np.int64))


@pytest.mark.parametrize(
    ("indptr", "indices", "message"),
    [
        ([0, 1, 2], [0, 0], "indices: column 1: the diagonal entry is missing"),
        ([0, 2, 3], [1, 0, 1], "indices: column 0: rows must increase strictly"),
        ([0, 1, 2], [0, 5], "indices: column 1: row 5 is outside the 2 x 2 matrix"),
        ([0, 1, 3], [0, 1], "indptr: expected offsets from 0 to the number of entries 2, got 0 to 3"),
        ([0, 5, 2], [0, 1], "indptr: offsets must not decrease nor pass the number of entries (column 0)"),
        ([0, -1, 2], [0, 1], "indptr: expected non-negative values, got -1 at index 1"),
        ([0], [], "indptr: must not be empty"),
    ],
)
def test_bad_sparse_patterns_name_the_argument(indptr: list[int], indices: list[int], message: str) -> None:
    with pytest.raises(InputError) as error:
        _pattern(indptr, indices)
    assert message in str(error.value)


@pytest.mark.parametrize(
    ("values", "rhs", "message"),
    [
        (np.array([1.0, np.nan]), np.ones(2), "values: non-finite value (NaN or infinity) at index 1"),
        (np.ones(3), np.ones(2), "values: expected 2 values, got 3"),
        (np.ones(2), np.ones(3), "rhs: expected 2 values, got 3"),
        (np.ones(2, np.float32), np.ones(2), "values: expected dtype float64, got float32"),
        (np.array([1.0, 0.0]), np.ones(2), "values: the matrix is singular (a zero pivot"),
    ],
)
def test_bad_sparse_solves_name_the_argument(values: np.ndarray, rhs: np.ndarray, message: str) -> None:
    with pytest.raises(InputError) as error:
        _pattern([0, 1, 2], [0, 1]).solve(values, rhs)
    assert message in str(error.value)
    if not message.startswith("rhs"):  # the same values are refused by factorize
        with pytest.raises(InputError) as error:
            _pattern([0, 1, 2], [0, 1]).factorize(values)
        assert message in str(error.value)


def test_a_kept_factor_refuses_a_right_hand_side_of_another_size() -> None:
    factor = _pattern([0, 1, 2], [0, 1]).factorize(np.array([2.0, 4.0]))
    np.testing.assert_array_equal(factor.solve(np.array([2.0, 2.0])), [1.0, 0.5])
    with pytest.raises(InputError, match="rhs: expected 2 values, got 3"):
        factor.solve(np.ones(3))


def tracking_call(**changes) -> dict:
    """The arguments of one valid ``_core.affine_lucas_kanade`` call, with ``changes``."""
    (before, gradient_x, gradient_y, after), start, initial, _ = random_tracking_pair(
        np.random.default_rng(1), ROWS, COLS, 3
    )
    call = {
        "before": before,
        "gradient_x": gradient_x,
        "gradient_y": gradient_y,
        "after": after,
        "start": start,
        "initial": initial,
        "window_px": (5, 3),
    }
    return call | changes


def with_nan(array: np.ndarray) -> np.ndarray:
    array = array.copy()
    array.flat[4] = np.nan
    return array


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"before": np.zeros((ROWS, COLS))}, "before: expected dtype float32, got float64"),
        (
            dict.fromkeys(["before", "gradient_x", "gradient_y", "after"], np.zeros((0, COLS), np.float32)),
            "before: must",
        ),
        (
            {"gradient_x": np.zeros((ROWS, COLS + 1), np.float32)},
            f"gradient_x: expected shape [{ROWS}, {COLS}] of float32, as before, got [{ROWS}, {COLS + 1}]",
        ),
        ({"after": np.zeros((ROWS, COLS), np.float32)[:, ::-1]}, "after: expected a C-contiguous array"),
        ({"start": np.zeros((3, 3), np.float32)}, "start: expected shape (N, 2) of float32 (x, y), got [3, 3]"),
        ({"initial": np.zeros((2, 2), np.float32)}, "initial: expected shape (3, 2) of float32 (x, y), as start"),
        ({"gradient_y": with_nan(np.zeros((ROWS, COLS), np.float32))}, "gradient_y: non-finite value"),
        ({"after": with_nan(np.zeros((ROWS, COLS), np.float32))}, "after: non-finite value"),
        ({"start": np.array([[1.0, np.inf]], np.float32), "initial": np.ones((1, 2), np.float32)}, "start: non-finite"),
        ({"initial": np.full((3, 2), np.nan, np.float32)}, "initial: non-finite value"),
        ({"window_px": (4, 3)}, "window_px: expected odd (width, height) sides from 3 to 1025, got [4, 3]"),
        ({"window_px": (1, 1)}, "window_px: expected odd (width, height) sides from 3 to 1025"),
        ({"window_px": (5, -3)}, "window_px: expected odd (width, height) sides >= 3, got -3"),
        ({"window_px": (5, 10**6 + 1)}, "window_px: expected odd (width, height) sides from 3 to 1025"),
        ({"max_iterations": -1}, "max_iterations: expected an integer >= 0, got -1"),
        ({"epsilon": np.nan}, "epsilon: expected a finite number >= 0 of pixels, got NaN"),
        ({"threads": 0}, "threads: expected 1 to 1024"),
    ],
)
def test_bad_tracking_arguments_name_the_argument(changes: dict, message: str) -> None:
    with pytest.raises(InputError) as error:
        _core.affine_lucas_kanade(**tracking_call(**changes))
    assert message in str(error.value)


def test_tracking_without_points_or_iterations() -> None:
    empty = np.zeros((0, 2), np.float32)
    tracked, ok, correlation = _core.affine_lucas_kanade(**tracking_call(start=empty, initial=empty))
    assert tracked.shape == (0, 2) and ok.shape == (0,) and correlation.shape == (0,)
    call = tracking_call(max_iterations=0)
    tracked, _, _ = _core.affine_lucas_kanade(**call)
    np.testing.assert_array_equal(tracked, call["initial"])


def splat_call(**changes) -> dict:
    """The arguments of one valid ``_core.splat_bilinear`` call, with ``changes``."""
    call = {
        "fine_col": np.array([1.5, 2.25, 0.5]),
        "fine_row": np.array([0.5, 1.0, 3.75]),
        "weight_real": np.ones(3),
        "weight_imag": np.zeros(3),
        "grid_shape": (ROWS, COLS),
    }
    return call | changes


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"fine_row": np.ones(2)}, "fine_row: expected shape (3,) of float64, as fine_col, got [2]"),
        ({"weight_real": np.ones(4)}, "weight_real: expected shape (3,) of float64, as fine_col, got [4]"),
        ({"weight_imag": np.ones(2)}, "weight_imag: expected shape (3,) of float64, as fine_col, got [2]"),
        ({"fine_col": np.ones((3, 1))}, "fine_col: expected shape (n,) of float64, got [3, 1]"),
        ({"weight_real": np.ones(3, np.float32)}, "weight_real: expected dtype float64, got float32"),
        ({"fine_row": np.ones(6)[::2]}, "fine_row: expected a C-contiguous array"),
        ({"fine_col": [1.0, 2.0, 3.0]}, "fine_col: expected a numpy array (n,) of float64, got list"),
        ({"fine_col": np.array([1.0, np.nan, 2.0])}, "fine_col: non-finite value (NaN or infinity) at index 1"),
        ({"fine_row": np.array([1.0, 2.0, -np.inf])}, "fine_row: non-finite value (NaN or infinity) at index 2"),
        ({"weight_real": np.array([np.inf, 0.0, 0.0])}, "weight_real: non-finite value (NaN or infinity) at index 0"),
        ({"weight_imag": np.array([0.0, np.nan, 0.0])}, "weight_imag: non-finite value (NaN or infinity) at index 1"),
        ({"grid_shape": (0, COLS)}, "grid_shape: expected (rows, cols), two positive integers, got (0, 10)"),
        ({"grid_shape": (ROWS, -1)}, "grid_shape: expected (rows, cols), two positive integers, got (12, -1)"),
        ({"grid_shape": (2**70, 1)}, "grid_shape: expected (rows, cols), two positive integers, got"),
        ({"grid_shape": (2.0, 3.0)}, "grid_shape: expected (rows, cols), two positive integers, got (2.0, 3.0)"),
        ({"grid_shape": (ROWS,)}, "grid_shape: expected (rows, cols), two positive integers, got (12,)"),
        ({"grid_shape": (2**31, 2)}, "grid_shape: expected (rows, cols), two positive integers of at most 2147483648"),
        ({"grid_shape": (2**40, 2**40)}, "grid_shape: expected (rows, cols), two positive integers of at most"),
    ],
)
def test_bad_splat_arguments_name_the_argument(changes: dict, message: str) -> None:
    with pytest.raises(InputError) as error:
        _core.splat_bilinear(**splat_call(**changes))
    assert message in str(error.value)


def test_splat_without_points() -> None:
    no_points = dict.fromkeys(["fine_col", "fine_row", "weight_real", "weight_imag"], np.zeros(0))
    real, imag = _core.splat_bilinear(**splat_call(**no_points))
    assert real.shape == imag.shape == (ROWS, COLS) and not real.any() and not imag.any()
