"""Procedural meshes with texture coordinates, written as MuJoCo XML ``<mesh>`` elements."""

from __future__ import annotations

import numpy as np


def lathe(strips: list[np.ndarray], segments: int = 32) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A surface of revolution about z from profile strips.

    Each strip is a polyline ``(M, 3)`` of ``(r, z, v)``: radius, height and the texture's v coordinate at
    that point; u runs once around (0 -> 1). Strips are separate so that sharp profile corners keep separate
    vertices (and so crisp shading). Faces are oriented so that walking along a strip, the outside lies on
    the right when seen with the axis on the left (for a cup profile: out along the bottom, up the outer
    wall, in across the rim, down the inner wall, in across the inner bottom).

    Returns:
        ``vertices (V, 3)``, ``faces (F, 3)`` int, ``texcoords (V, 2)``.
    """
    verts, uvs, faces = [], [], []
    theta = np.linspace(0.0, 2 * np.pi, segments + 1)
    base = 0
    for strip in strips:
        strip = np.asarray(strip, dtype=np.float64)
        M = len(strip)
        r, z, v = strip[:, 0], strip[:, 1], strip[:, 2]
        # ring index k (with the seam duplicated at k = segments), profile index j
        x = r[None, :] * np.cos(theta)[:, None]
        y = r[None, :] * np.sin(theta)[:, None]
        zz = np.broadcast_to(z[None, :], x.shape)
        verts.append(np.stack([x, y, zz], -1).reshape(-1, 3))
        uu = np.broadcast_to((theta / (2 * np.pi))[:, None], x.shape)
        vv = np.broadcast_to(v[None, :], x.shape)
        uvs.append(np.stack([uu, vv], -1).reshape(-1, 2))

        def idx(k, j, base=base, M=M):
            return base + k * M + j

        for k in range(segments):
            for j in range(M - 1):
                a, b, c, d = idx(k, j), idx(k + 1, j), idx(k + 1, j + 1), idx(k, j + 1)
                if r[j] > 1e-9:
                    faces.append((a, b, c))
                if r[j + 1] > 1e-9:
                    faces.append((a, c, d))
        base += (segments + 1) * M
    return np.concatenate(verts), np.asarray(faces, dtype=np.int64), np.concatenate(uvs)


def mesh_xml(name: str, vertices: np.ndarray, faces: np.ndarray, texcoords: np.ndarray | None = None) -> str:
    """A MuJoCo ``<mesh>`` asset element holding the given arrays inline."""

    def fmt(a):
        return " ".join(f"{x:.6g}" for x in np.asarray(a).ravel())

    tex = f' texcoord="{fmt(texcoords)}"' if texcoords is not None else ""
    return (
        f'<mesh name="{name}" vertex="{fmt(vertices)}" face="{" ".join(str(int(i)) for i in faces.ravel())}"'
        f'{tex} inertia="shell"/>'
    )


def cup_profile(
    height: float, r_bottom: float, r_top: float, wall: float, bottom: float, bulge: float = 0.0, n: int = 8
) -> list[np.ndarray]:
    """Profile strips of a cup: outer bottom, outer wall, rim, inner wall, inner bottom.

    The outer wall's radius runs linearly from ``r_bottom`` to ``r_top`` plus ``bulge * sin(pi z / height)``.
    Texture v: the outer wall spans v in [0.25, 1]; the inside and the bottom use v in [0, 0.25), where
    :func:`s3k.sim.textures.cup_texture` keeps a plain colour.
    """
    z = np.linspace(0.0, height, n)
    r_out = r_bottom + (r_top - r_bottom) * z / height + bulge * np.sin(np.pi * z / height)
    zi = np.linspace(height, bottom, n)
    r_in = r_out[::-1] - wall
    outer_bottom = np.array([[0.0, 0.0, 0.02], [r_bottom, 0.0, 0.05]])
    outer_wall = np.stack([r_out, z, 0.25 + 0.75 * z / height], 1)
    rim = np.array([[r_out[-1], height, 0.22], [r_in[0], height, 0.2]])
    inner_wall = np.stack([r_in, zi, 0.2 - 0.1 * (height - zi) / height], 1)
    inner_bottom = np.array([[r_in[-1], bottom, 0.08], [0.0, bottom, 0.05]])
    return [outer_bottom, outer_wall, rim, inner_wall, inner_bottom]


def cup_radius(height: float, r_bottom: float, r_top: float, bulge: float, z: float) -> float:
    """Outer radius of :func:`cup_profile`'s wall at height ``z``."""
    return r_bottom + (r_top - r_bottom) * z / height + bulge * np.sin(np.pi * z / height)
