"""Finite-element mechanics of one tissue cross-section pressed by a flat ultrasound probe.

What is modelled
----------------
* A rectangular section (x lateral, z depth; mm) in **plane strain**, bottom fixed, sides and the
  surface beside the probe traction-free.
* The probe is a rigid face 37.5 mm wide centred at x = 0, pressed down by a displacement
  ``lambda`` (mm). Contact under the face is either *sticking* (u_x held, u_z = the face's depth) or
  frictionless *sliding* (only u_z). A flat level face touches the whole surface under it at lambda = 0
  and stays in full contact (under a flat punch the contact pressure is compressive everywhere). A face
  tilted to the surface (``face_tilt_deg``: a tilted probe or an inclined surface) or convex
  (``face_radius_mm``) meets it progressively: lambda counts from first contact, and at each step an
  active set holds the face nodes the face has reached, adds a free node that would lie above the face
  and releases a held node that would pull on it (a sticking node keeps the lateral position at which it
  was caught). The face moves along the surface normal, or at ``face_travel_deg`` to it, when a sticking
  face drags the surface sideways as it goes.
* Material: a compressible **Yeoh hyperelastic** law (Yeoh 1993, Rubber Chem. Technol. 66:754)
  ``W = mu/2 (x + c2 x^2 + c3 x^3) + kappa/4 (J^2 - 1 - 2 ln J)``, ``x = I1bar - 3``
  (isochoric first invariant of the plane-strain C, J = det F). ``mu`` is the small-strain shear
  modulus (so C10 = mu/2), ``c2 = C20/C10`` and ``c3 = C30/C10`` are dimensionless. ``c2 = c3 = 0``
  is neo-Hookean; ``c2, c3 > 0`` give strong strain-stiffening (the soft phantom: the CAE blue
  phantom is a rubber-like elastomer, and Yeoh is the usual law for rubbers and tissue-mimicking
  elastomers); ``c2 < 0 < c3`` (the classic filled-rubber shape) softens mildly at moderate strain
  and stiffens at large strain, which keeps the law stable at the singular probe edges (the stiff
  phantom). ``kappa`` follows from ``mu`` and the small-strain Poisson ratio. Neo-Hookean alone
  stiffens only mildly (5-8 % of k over the paper's indentations, mostly because the layer under
  the probe thins), too little for the soft phantom and too much for the stiff one.
* The vessel is a circular **soft inclusion** (same law, moduli times ``lumen_stiffness_ratio``,
  default 1/20; no self-contact), meshed conformingly, so that the displacement field is defined
  everywhere in the section. The inclusion does not conserve its volume: the phantom vessel is open
  at its ends, so fluid leaves as it collapses. An optional lumen pressure acts as the isotropic
  Cauchy stress ``-p I`` inside the lumen, which by the divergence theorem is exactly a follower
  pressure ``p`` on the lumen wall. It is ramped up at lambda = 0 with the probe face already held
  at z = 0: the reference circle is the unpressurised lumen, the lambda = 0 state is distended, and
  ``force_n[0]`` is the reaction of the pressurised vessel on the probe, not zero.
* Optional layers (skin / fat / muscle) from the surface downward, each with its own moduli.
* Quasi-static load stepping in lambda, Newton on P2 (quadratic) triangles (a Delaunay mesh
  of a triangular lattice with rings of nodes on and around the lumen wall), with increment
  halving when Newton fails; the contact force is the reaction on the probe face (N per mm out of
  plane) times an effective out-of-plane width. Each Newton step is assembled by the compiled element
  loop (``usdeform._core.HyperelasticSection``) and solved by a sparse LDL^T in Rust
  (``usdeform._core.SymmetricSolver``, its ordering computed once per section); the last steps of a
  load step, once they are small and contracting, reuse the tangent's factor (modified Newton, run to
  full Newton's accuracy: the converged state within 1e-13 mm of full Newton's), about 30 % less CPU.

What is left out (on purpose; candidates for a sim-to-real diagnosis)
----------------------------------------------------------------------
Out-of-plane (3D) deformation beyond the effective width, rounded probe edges, the lateral shift of a
face's contact region as it travels obliquely, friction other than the two limits stick / frictionless
slide, self-contact of a collapsed lumen, viscoelasticity and rate effects, gravity, fluid flow out of
the vessel, and any pre-stress of the phantom.

Scaling
-------
All loads are displacements (plus the lumen pressure), so multiplying every modulus (and the
lumen pressure) by a factor ``s`` leaves the displacement field unchanged and multiplies the force
by ``s``. :meth:`MechanicsSolution.scaled` exploits this; :mod:`usdeform.sim.phantoms` uses it to
serve many sweep positions from a few solves.

Units: mm, kPa for moduli and pressure, N for forces.
"""

from __future__ import annotations

from .mesh import section_mesh
from .section import PROBE_WIDTH_MM, Layer, MechanicsConvergenceError, SectionSpec, Vessel
from .solution import MAX_INDENTATION_FRACTION, MechanicsSolution, cache_dir, solution_is_cached, solve_section

__all__ = [
    "MAX_INDENTATION_FRACTION",
    "PROBE_WIDTH_MM",
    "Layer",
    "MechanicsConvergenceError",
    "MechanicsSolution",
    "SectionSpec",
    "Vessel",
    "cache_dir",
    "section_mesh",
    "solution_is_cached",
    "solve_section",
]
