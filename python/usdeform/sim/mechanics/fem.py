"""The finite-element solve: Yeoh plane-strain material, P2 elements (the element loop in the compiled core,
:class:`usdeform._core.HyperelasticSection`), Newton with load continuation."""

from __future__ import annotations

import numpy as np
from skfem import Basis, ElementTriP2, ElementVector

from ... import _core
from ...errors import InputError
from .mesh import section_mesh
from .section import MechanicsConvergenceError, SectionSpec

_KPA_TO_N_PER_MM2 = 1e-3
_MAX_NEWTON_ITERATIONS = 12  # converged steps take 3-5; more means the increment is too large
_FIRST_INCREMENT_MM = 0.5  # first lambda increment from the unloaded state (no predictor yet), mm
_MAX_STEP_HALVINGS = 6
_CONTACT_TOLERANCE_MM = 1e-6  # a node within this of the face's height is at it
_MAX_CONTACT_PASSES = 8
_STEP_TOLERANCE = 1e-9  # converged: a Newton step below this (times max(1, lambda)), mm, and the residual small
_REUSED_FACTOR_TOLERANCE = 1e-12  # ... with a kept factor
_REUSE_TANGENT_BELOW_MM = 1e-3  # a Newton step below this (times max(1, lambda)) keeps its tangent's factor
_REUSE_CONTRACTION = 0.1  # ... when it is also below this share of the step before
_REUSED_STEP_CONTRACTION = 0.01  # a step with a kept factor is taken when below this share of the step before
_KEPT_FACTOR_ITERATIONS = 2  # the steps with a kept factor stand for full Newton's last (quadratic) iterations


class _SectionProblem:
    """The discretised section: mesh, P2 basis, per-element materials and boundary DOFs."""

    def __init__(self, spec: SectionSpec):
        self.spec = spec
        self.mesh, self.in_lumen, material_index = section_mesh(spec)
        self.basis = Basis(self.mesh, ElementVector(ElementTriP2()), intorder=4)
        moduli = np.array([layer.shear_modulus_kpa for layer in spec.layers] + [spec.shear_modulus_kpa])
        c2 = np.array([layer.yeoh_c2 for layer in spec.layers] + [spec.yeoh_c2])
        c3 = np.array([layer.yeoh_c3 for layer in spec.layers] + [spec.yeoh_c3])
        centroid_x = self.mesh.p[0, self.mesh.t].mean(axis=0)
        shear = (
            moduli[material_index]
            * spec.lumen_modulus_factor(self.mesh.p[:, self.mesh.t].mean(axis=1).T)
            * spec.lateral_factor(centroid_x)
        )
        self.shear_modulus = (shear * _KPA_TO_N_PER_MM2)[:, None]
        self.yeoh_c2, self.yeoh_c3 = c2[material_index][:, None], c3[material_index][:, None]
        self.bulk_modulus = self.shear_modulus * spec.bulk_modulus_ratio
        self.lumen_pressure = (np.where(self.in_lumen, spec.lumen_pressure_kpa, 0.0) * _KPA_TO_N_PER_MM2)[:, None]
        self.pressure_fraction = 1.0  # share of the lumen pressure applied (ramped up at lambda = 0)

        tolerance = 1e-6 * spec.mesh_size_mm
        half_probe = spec.probe_width_mm / 2
        bottom = self.basis.get_dofs(lambda x: x[1] > spec.depth_mm - tolerance)
        face = self.basis.get_dofs(lambda x: (x[1] < tolerance) & (np.abs(x[0]) < half_probe + tolerance))
        self.face_z_dofs = face.all("u^2")
        self.face_x_dofs = face.all("u^1")  # in the same node order as face_z_dofs
        self.progressive = not spec.face_is_flat_and_level
        self.travel_slope = np.tan(np.radians(spec.face_travel_deg))  # lateral face travel per mm of lambda
        if self.progressive:  # face DOFs held per step as they come into contact (solve_step)
            self.face_gap_mm = spec.face_gap_mm(self.basis.doflocs[0, self.face_z_dofs])
            self.fixed_dofs = bottom.all()
            # the accepted contact set and, per sticking node, u_x - slope * lambda at which it is held
            self.in_contact = np.zeros(len(self.face_z_dofs), dtype=bool)
            self.stick_anchor_mm = np.zeros(len(self.face_z_dofs))
        else:
            held_x = self.face_x_dofs if spec.contact == "stick" else np.array([], dtype=np.int64)
            self.fixed_dofs = np.unique(np.concatenate([bottom.all(), self.face_z_dofs, held_x]))
        self.free_dofs = np.setdiff1d(np.arange(self.basis.N), self.fixed_dofs)

        # The element loop is the compiled core's (skfem's forms loop over the 144 pairs of local basis functions in
        # Python): the P2 vector dofs are interleaved (x, z) per scalar dof, so the scalar shape-function gradients
        # and the quadrature weights are all it needs.
        scalar = Basis(self.mesh, ElementTriP2(), intorder=4)
        n_elements = scalar.nelems
        local = 2 * scalar.element_dofs.T[:, :, None] + np.arange(2)  # (n_elements, 6, 2): vector dof of (i, c)
        element_dofs = local.reshape(n_elements, 12)
        free_index = np.full(self.basis.N, -1)
        free_index[self.free_dofs] = np.arange(len(self.free_dofs))
        rows, cols = np.broadcast_arrays(free_index[element_dofs][:, :, None], free_index[element_dofs][:, None, :])
        free_entries = np.flatnonzero((rows >= 0) & (cols >= 0))  # element-matrix entries in K_ff
        keys = rows.ravel()[free_entries] * len(self.free_dofs) + cols.ravel()[free_entries]
        pattern, entry_slot = np.unique(keys, return_inverse=True)  # CSR order; K_ff is symmetric
        entry_slots = np.full(n_elements * 144, -1, dtype=np.int64)
        entry_slots[free_entries] = entry_slot
        indptr = np.searchsorted(pattern // len(self.free_dofs), np.arange(len(self.free_dofs) + 1))
        self.solver = _core.SymmetricSolver(indptr.astype(np.int64), (pattern % len(self.free_dofs)).astype(np.int64))
        gradients = np.stack([np.asarray(scalar.basis[i][0].grad) for i in range(6)])  # (6, 2, n_elements, n_points)
        self.assembly = _core.HyperelasticSection(
            self.basis.N,
            element_dofs.astype(np.int64),
            np.ascontiguousarray(gradients.transpose(2, 3, 0, 1)),
            np.ascontiguousarray(scalar.dx, dtype=np.float64),
            np.ascontiguousarray(self.shear_modulus[:, 0]),
            np.ascontiguousarray(self.yeoh_c2[:, 0]),
            np.ascontiguousarray(self.yeoh_c3[:, 0]),
            np.ascontiguousarray(self.bulk_modulus[:, 0]),
            np.ascontiguousarray(self.lumen_pressure[:, 0]),
            entry_slots.reshape(n_elements, 144),
            len(pattern),
        )
        self.entry_row, self.entry_column = pattern // len(self.free_dofs), pattern % len(self.free_dofs)
        self.free_index = free_index

    def internal_force_and_tangent(self, u: np.ndarray, with_tangent: bool = True):
        """Internal nodal forces (N/mm, per mm out of plane; (n_dofs,)) and, optionally, the entries
        of the free-free block of the tangent matrix in the pattern of ``self.solver``. Raises
        FloatingPointError for a non-finite ``u`` or an inverted element (det F <= 0)."""
        if not np.all(np.isfinite(u)):
            raise FloatingPointError("non-finite displacement")
        force, values, det = self.assembly.assemble(u, self.pressure_fraction, with_tangent)
        if det <= 0:
            raise FloatingPointError("inverted element (J <= 0)")
        return force, values

    def solve_step(self, u_guess: np.ndarray, probe_displacement: float) -> tuple[np.ndarray, int]:
        """The state at one lambda from ``u_guess``; returns (u, Newton iterations).

        A flat level face holds its nodes at u_z = lambda (and, sticking, u_x = lambda * tan(face_travel)). A face
        that meets the surface progressively holds the nodes it has reached at the face: those in contact at the
        last solved step and those whose depth u_z in ``u_guess`` is at or above the face's; a sticking node keeps
        the lateral position at which it was caught, moved with the face's lateral travel. The contact set is then
        corrected until no free node is above the face and no held node pulls on it (an active set), and kept for
        the next step. Raises FloatingPointError when the iterations invert an element, diverge or stall, or the
        contact set does not settle.
        """
        if not self.progressive:
            u = u_guess.copy()
            u[self.fixed_dofs] = 0.0
            u[self.face_z_dofs] = probe_displacement
            if self.spec.contact == "stick" and self.travel_slope:
                u[self.face_x_dofs] = self.travel_slope * probe_displacement
            return self._newton(u, np.zeros(len(self.free_dofs), dtype=bool), probe_displacement)
        face_depth = probe_displacement - self.face_gap_mm  # depth of the face over each face node, mm
        u = u_guess.copy()
        u[self.fixed_dofs] = 0.0
        reached = u[self.face_z_dofs] <= face_depth + _CONTACT_TOLERANCE_MM  # the face is at or past them
        in_contact = self.in_contact | reached
        anchor = np.where(
            self.in_contact, self.stick_anchor_mm, u[self.face_x_dofs] - self.travel_slope * probe_displacement
        )
        total = 0
        for _ in range(_MAX_CONTACT_PASSES):
            u[self.face_z_dofs[in_contact]] = face_depth[in_contact]
            held = self.face_z_dofs[in_contact]
            if self.spec.contact == "stick":
                u[self.face_x_dofs[in_contact]] = anchor[in_contact] + self.travel_slope * probe_displacement
                held = np.concatenate([held, self.face_x_dofs[in_contact]])
            constrained = np.zeros(len(self.free_dofs), dtype=bool)
            constrained[self.free_index[held]] = True
            u, iterations = self._newton(u, constrained, probe_displacement)
            total += iterations
            force, _ = self.internal_force_and_tangent(u, with_tangent=False)
            reaction = force[self.face_z_dofs]
            scale = np.abs(reaction).max() + 1e-12
            joining = ~in_contact & (u[self.face_z_dofs] < face_depth - _CONTACT_TOLERANCE_MM)  # above the face
            leaving = in_contact & (reaction < -1e-6 * scale)
            if not (joining.any() or leaving.any()):
                self.in_contact = in_contact
                self.stick_anchor_mm = np.where(in_contact, anchor, 0.0)
                return u, total
            anchor[joining] = u[self.face_x_dofs[joining]] - self.travel_slope * probe_displacement
            in_contact = (in_contact & ~leaving) | joining
        raise FloatingPointError(f"the contact set did not settle in {_MAX_CONTACT_PASSES} passes")

    def _newton(self, u: np.ndarray, constrained: np.ndarray, probe_displacement: float) -> tuple[np.ndarray, int]:
        """Newton iterations from ``u`` with the fixed DOFs and the ``constrained`` free DOFs (a mask over
        ``free_dofs``) held at their values in ``u``; returns (u, iterations as full Newton counts them: the
        factorisations, plus at most ``_KEPT_FACTOR_ITERATIONS`` for the steps with a kept factor).

        The tangent is factorised at every iteration until a step is below ``_REUSE_TANGENT_BELOW_MM`` (times
        max(1, lambda)) and, after the first, smaller than ``_REUSE_CONTRACTION`` of the step before: from there the
        tangent changes by about that step's strain, so its last factorisation solves the next steps at a
        contraction of about that size (modified Newton). A step with the kept factor is taken only where it is
        below ``_REUSED_STEP_CONTRACTION`` of the step before, else the tangent is factorised again and the step
        solved with it; and as it converges linearly, steps with a kept factor run until one is below
        ``_REUSED_FACTOR_TOLERANCE`` (full Newton's: ``_STEP_TOLERANCE``, which its quadratic last step overshoots
        by orders of magnitude), so that the state is full Newton's within round-off: the contact set that
        follows is decided on it."""
        u = u.copy()
        free = self.free_dofs
        moving = free[~constrained]
        held = free[constrained]
        if constrained.any():  # held rows and columns of K_ff become identity's, their steps zero
            held_entry = constrained[self.entry_row] | constrained[self.entry_column]
            held_diagonal = held_entry & (self.entry_row == self.entry_column)
        scale = max(1.0, abs(probe_displacement))
        factor: _core.SymmetricFactor | None = None
        previous_step = np.inf
        factorisations = kept_factor_steps = 0

        def iterations() -> int:
            """The iterations so far, as full Newton counts them."""
            return factorisations + min(kept_factor_steps, _KEPT_FACTOR_ITERATIONS)

        while iterations() < _MAX_NEWTON_ITERATIONS:
            force, stiffness = self.internal_force_and_tangent(u, with_tangent=factor is None)
            reaction_scale = np.abs(np.concatenate([force[self.fixed_dofs], force[held]])).max() + 1e-12
            right_side = -force[free]
            if constrained.any():
                right_side[constrained] = 0.0
            reused = False
            try:
                if factor is not None:
                    step = factor.solve(right_side)
                    reused = bool(np.abs(step).max() < _REUSED_STEP_CONTRACTION * previous_step)
                    if not reused:
                        factor = None
                        _, stiffness = self.internal_force_and_tangent(u)
                if factor is None:
                    if constrained.any():
                        stiffness[held_entry] = 0.0
                        stiffness[held_diagonal] = 1.0
                    factor = self.solver.factorize(stiffness)
                    step = factor.solve(right_side)
            except InputError as singular:
                raise FloatingPointError(f"singular tangent: {singular}") from singular
            factorisations += not reused
            kept_factor_steps += reused
            u[free] += step
            step_size = np.abs(step).max()
            tolerance = (_REUSED_FACTOR_TOLERANCE if reused else _STEP_TOLERANCE) * scale
            if step_size < tolerance and np.abs(force[moving]).max() < 1e-6 * reaction_scale:
                return u, iterations()
            if step_size > 1e3 * scale:
                raise FloatingPointError("Newton diverged")
            if not (step_size < _REUSE_TANGENT_BELOW_MM * scale and step_size < _REUSE_CONTRACTION * previous_step):
                factor = None
            previous_step = step_size
        raise FloatingPointError(f"no convergence in {iterations()} iterations")

    def probe_force(self, u: np.ndarray) -> float:
        """Contact force (N, compression positive) of the solved state ``u``."""
        force, _ = self.internal_force_and_tangent(u, with_tangent=False)
        return float(force[self.face_z_dofs].sum() * self.spec.out_of_plane_width_mm)


def _continuation(
    solve,
    start: float,
    target: float,
    u_start: np.ndarray,
    what: str,
    before_start: tuple | None = None,
    first_increment: float | None = None,
) -> tuple[np.ndarray, int, tuple[np.ndarray, float]]:
    """Follow ``solve(guess, load) -> (u, iterations)`` from load ``start`` to ``target``.

    Tries the whole increment first, halves it when Newton fails and doubles it after an easy
    increment (at most 4 iterations); the predictor extrapolates
    the last converged increment linearly (``before_start``: the (u, load) converged before
    ``start``, if any; without it the first increment is at most ``first_increment``). Returns (u
    at target, iterations, the (u, load) converged before target, for the next call). Raises
    MechanicsConvergenceError naming ``what``.
    """
    u_previous, load_previous = before_start if before_start is not None else (u_start, start)
    u_current, load_current = u_start, start
    increment, halvings, iterations = target - start, 0, 0
    if before_start is None and first_increment is not None:
        increment = min(increment, first_increment)
    while load_current < target:
        load_next = min(load_current + increment, target)
        guess = u_current
        if load_current > load_previous:
            guess = u_current + (load_next - load_current) / (load_current - load_previous) * (u_current - u_previous)
        try:
            u_next, n_iterations = solve(guess, load_next)
        except FloatingPointError as failure:
            halvings += 1
            if halvings > _MAX_STEP_HALVINGS:
                raise MechanicsConvergenceError(
                    f"Newton failed at {what} (reached {load_current:.4g} of {target:.4g}, increment halved "
                    f"{halvings - 1} times): {failure}"
                ) from failure
            increment /= 2
            continue
        iterations += n_iterations
        if n_iterations <= 4:  # easy increment: try a larger one next
            increment *= 2
        u_previous, load_previous = u_current, load_current
        u_current, load_current = u_next, load_next
    return u_current, iterations, (u_previous, load_previous)


def _solve_uncached(spec: SectionSpec, probe_displacement_mm: np.ndarray) -> dict[str, np.ndarray]:
    problem = _SectionProblem(spec)
    n_steps = len(probe_displacement_mm)
    history = np.zeros((n_steps, problem.basis.N))
    forces = np.zeros(n_steps)
    iterations = np.zeros(n_steps, dtype=np.int64)

    def pressurised(guess, fraction):
        problem.pressure_fraction = fraction
        return problem.solve_step(guess, 0.0)

    # Step 0: lambda = 0, probe face held at z = 0, lumen pressure ramped up from zero.
    u, iterations[0], _ = _continuation(
        pressurised, 0.0, 1.0, history[0], f"load step 0 (lambda = 0 mm, lumen pressure {spec.lumen_pressure_kpa} kPa)"
    )
    history[0], forces[0] = u, problem.probe_force(u)
    before = None
    for index in range(1, n_steps):
        lam_start, lam_target = probe_displacement_mm[index - 1], probe_displacement_mm[index]
        what = f"load step {index} (lambda {lam_start:.4g} -> {lam_target:.4g} mm)"
        u, iterations[index], before = _continuation(
            problem.solve_step, lam_start, lam_target, u, what, before, _FIRST_INCREMENT_MM
        )
        history[index], forces[index] = u, problem.probe_force(u)
    return {
        "nodes": problem.mesh.p,
        "elements": problem.mesh.t,
        "in_lumen": problem.in_lumen,
        "displacement_dofs": history,
        "force_n": forces,
        "newton_iterations": iterations,
    }
