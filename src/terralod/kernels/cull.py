"""Patch culling kernels (Hu & Wang §3.2): does any triangle of a patch face the eye?"""

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
        wx, wy, wz = (
            vertices[c, 0] - vertices[b, 0],
            vertices[c, 1] - vertices[b, 1],
            vertices[c, 2] - vertices[b, 2],
        )
        nx = uy * wz - uz * wy
        ny = uz * wx - ux * wz
        nz = ux * wy - uy * wx
        if nx * (ex - ax) + ny * (ey - ay) + nz * (ez - az) >= 0.0:
            return True
    return False


@jit
def min_distance_to_triangles(vertices, triangles, px, py, pz):
    """Smallest Euclidean distance from the point (px, py, pz) to any triangle of the mesh (the closest
    point on each triangle by Voronoi regions of its vertices, edges and face; Ericson, Real-Time Collision
    Detection §5.1.5). The renderer's near plane is set from it, so nothing drawn is clipped."""
    best = 1e300
    for k in range(triangles.shape[0]):
        a = triangles[k, 0]
        b = triangles[k, 1]
        c = triangles[k, 2]
        ax, ay, az = vertices[a, 0], vertices[a, 1], vertices[a, 2]
        abx, aby, abz = vertices[b, 0] - ax, vertices[b, 1] - ay, vertices[b, 2] - az
        acx, acy, acz = vertices[c, 0] - ax, vertices[c, 1] - ay, vertices[c, 2] - az
        apx, apy, apz = px - ax, py - ay, pz - az
        d1 = abx * apx + aby * apy + abz * apz
        d2 = acx * apx + acy * apy + acz * apz
        bpx, bpy, bpz = px - vertices[b, 0], py - vertices[b, 1], pz - vertices[b, 2]
        d3 = abx * bpx + aby * bpy + abz * bpz
        d4 = acx * bpx + acy * bpy + acz * bpz
        cpx, cpy, cpz = px - vertices[c, 0], py - vertices[c, 1], pz - vertices[c, 2]
        d5 = abx * cpx + aby * cpy + abz * cpz
        d6 = acx * cpx + acy * cpy + acz * cpz
        va = d3 * d6 - d5 * d4
        vb = d5 * d2 - d1 * d6
        vc = d1 * d4 - d3 * d2
        if d1 <= 0.0 and d2 <= 0.0:  # vertex A
            qx, qy, qz = ax, ay, az
        elif d3 >= 0.0 and d4 <= d3:  # vertex B
            qx, qy, qz = vertices[b, 0], vertices[b, 1], vertices[b, 2]
        elif d6 >= 0.0 and d5 <= d6:  # vertex C
            qx, qy, qz = vertices[c, 0], vertices[c, 1], vertices[c, 2]
        elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:  # edge AB
            t = d1 / (d1 - d3)
            qx, qy, qz = ax + t * abx, ay + t * aby, az + t * abz
        elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:  # edge AC
            t = d2 / (d2 - d6)
            qx, qy, qz = ax + t * acx, ay + t * acy, az + t * acz
        elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:  # edge BC
            t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            qx = vertices[b, 0] + t * (vertices[c, 0] - vertices[b, 0])
            qy = vertices[b, 1] + t * (vertices[c, 1] - vertices[b, 1])
            qz = vertices[b, 2] + t * (vertices[c, 2] - vertices[b, 2])
        else:  # face
            den = va + vb + vc
            if den == 0.0:  # degenerate triangle: its vertex A stands for it
                qx, qy, qz = ax, ay, az
            else:
                v = vb / den
                w = vc / den
                qx, qy, qz = ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w
        dx, dy, dz = px - qx, py - qy, pz - qz
        d = dx * dx + dy * dy + dz * dz
        if d < best:
            best = d
    return best**0.5
