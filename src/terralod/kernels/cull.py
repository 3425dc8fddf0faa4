"""Patch culling kernels (paper 001 §3.2): does any triangle of a patch face the eye?"""

from __future__ import annotations

from terralod.kernels import jit


@jit
def any_front_facing(vertices, triangles, ex, ey, ez):
    """True when some triangle ABC (counter-clockwise from its front) has G = n . (eye - A) >= 0 with
    n = (B - A) x (C - B); stops at the first one, so a patch seen from its front costs a few triangles."""
    for k in range(triangles.shape[0]):
        a = triangles[k, 0]
        b = triangles[k, 1]
        c = triangles[k, 2]
        ax, ay, az = vertices[a, 0], vertices[a, 1], vertices[a, 2]
        ux, uy, uz = vertices[b, 0] - ax, vertices[b, 1] - ay, vertices[b, 2] - az
        wx, wy, wz = vertices[c, 0] - vertices[b, 0], vertices[c, 1] - vertices[b, 1], vertices[c, 2] - vertices[b, 2]
        nx = uy * wz - uz * wy
        ny = uz * wx - ux * wz
        nz = ux * wy - uy * wx
        if nx * (ex - ax) + ny * (ey - ay) + nz * (ez - az) >= 0.0:
            return True
    return False
