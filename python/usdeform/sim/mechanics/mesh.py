"""Meshing of a section: a Delaunay triangulation conforming to the lumen, layers and probe edges."""

from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial import Delaunay
from skfem import MeshTri

from .section import SectionSpec


def section_mesh(spec: SectionSpec) -> tuple[MeshTri, np.ndarray, np.ndarray]:
    """Triangulate the section conformingly to the lumen circles, the layer interfaces and the probe edges.

    Returns the mesh (node coordinates in mm, x lateral, z depth), a boolean per element that is
    True inside a lumen (the main vessel's or an extra vessel's), and the material index per element
    (0..len(layers)-1 for the layers, len(layers) for the base material below them).
    """
    h = spec.mesh_size_mm
    half_width, half_probe = spec.width_mm / 2, spec.probe_width_mm / 2
    # Lateral node positions: the probe edges are nodes, so the probe face is a union of edges.
    x_nodes = np.concatenate(
        [
            np.linspace(-half_width, -half_probe, max(2, int(np.ceil((half_width - half_probe) / h)) + 1))[:-1],
            np.linspace(-half_probe, half_probe, max(2, int(np.ceil(spec.probe_width_mm / h)) + 1))[:-1],
            np.linspace(half_probe, half_width, max(2, int(np.ceil((half_width - half_probe) / h)) + 1)),
        ]
    )
    x_offset = np.concatenate([[x_nodes[0]], 0.5 * (x_nodes[1:] + x_nodes[:-1]), [x_nodes[-1]]])
    # Depth rows: layer interfaces are rows; rows about h*sqrt(3)/2 apart (equilateral-ish triangles).
    interfaces = np.concatenate([[0.0], np.cumsum([layer.thickness_mm for layer in spec.layers]), [spec.depth_mm]])
    row_spacing = h * np.sqrt(3) / 2
    z_rows = np.unique(
        np.concatenate(
            [
                np.linspace(a, b, max(2, int(np.ceil((b - a) / row_spacing)) + 1))
                for a, b in itertools.pairwise(interfaces)
            ]
        )
    )
    points = np.concatenate(
        [
            np.column_stack([x_nodes if i % 2 == 0 else x_offset, np.full(len(x_nodes) + (i % 2), z)])
            for i, z in enumerate(z_rows)
        ]
    )
    # Replace lattice points near each lumen wall by points on the wall and on two rings either side.
    lumens = spec.lumens
    for centre_x, centre_depth, radius, _ in lumens:
        distance = np.linalg.norm(points - np.array([centre_x, centre_depth]), axis=1)
        points = points[np.abs(distance - radius) > 0.75 * h]
    ring_points = []
    for centre_x, centre_depth, radius, _ in lumens:
        rings = [radius]
        if radius - 0.75 * h > 0.5 * h:
            rings.append(radius - 0.75 * h)
        rings.append(radius + 0.75 * h)
        n_wall = max(12, int(np.ceil(2 * np.pi * radius / h)))
        angles = 2 * np.pi * np.arange(n_wall) / n_wall
        ring_points += [
            np.array([centre_x, centre_depth])
            + r * np.column_stack([np.cos(angles + k * np.pi / n_wall), np.sin(angles + k * np.pi / n_wall)])
            for k, r in enumerate(rings)
        ]
    points = np.concatenate([points, *ring_points])
    triangles = Delaunay(points).simplices
    corners = points[triangles]
    signed_area = 0.5 * (
        (corners[:, 1, 0] - corners[:, 0, 0]) * (corners[:, 2, 1] - corners[:, 0, 1])
        - (corners[:, 2, 0] - corners[:, 0, 0]) * (corners[:, 1, 1] - corners[:, 0, 1])
    )
    triangles = triangles[np.abs(signed_area) > 1e-9 * h * h]
    mesh = MeshTri(points.T.copy(), triangles.T.copy())
    centroids = mesh.p[:, mesh.t].mean(axis=1)
    in_lumen = spec.lumen_index(centroids.T) >= 0
    material = np.searchsorted(interfaces[1:-1], centroids[1], side="right")
    return mesh, in_lumen, material


# ----------------------------------------------------------------------------------------------
