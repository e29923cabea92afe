"""Quaternion ``@wp.func`` helpers shared by the kernel families (w, x, y, z order, ``docs/conventions.md``)."""

import warp as wp

__all__ = ["quat_multiply", "quat_conjugate", "quat_to_matrix", "quat_from_rotation_matrix"]


@wp.func
def quat_multiply(a: wp.vec4, b: wp.vec4):
    """Hamilton product ``a * b`` of (w, x, y, z) quaternions (apply ``b`` first, then ``a``)."""
    return wp.vec4(
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    )


@wp.func
def quat_conjugate(q: wp.vec4):
    """Conjugate of a (w, x, y, z) quaternion: the inverse rotation of a unit one."""
    return wp.vec4(q[0], -q[1], -q[2], -q[3])


@wp.func
def quat_to_matrix(q: wp.vec4):
    """Rotation matrix of a unit (w, x, y, z) quaternion (normalize first where it may not be)."""
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    return wp.mat33(
        1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
        2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
        2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y),
    )


@wp.func
def quat_from_rotation_matrix(r: wp.mat33):
    """Unit (w, x, y, z) quaternion of a rotation matrix (Shepperd: pivot on the largest of 4 candidates)."""
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    q = wp.vec4(0.0, 0.0, 0.0, 0.0)
    if trace >= r[0, 0] and trace >= r[1, 1] and trace >= r[2, 2]:
        q = wp.vec4(1.0 + trace, r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1])
    elif r[0, 0] >= r[1, 1] and r[0, 0] >= r[2, 2]:
        q = wp.vec4(r[2, 1] - r[1, 2], 1.0 + 2.0 * r[0, 0] - trace, r[0, 1] + r[1, 0], r[0, 2] + r[2, 0])
    elif r[1, 1] >= r[2, 2]:
        q = wp.vec4(r[0, 2] - r[2, 0], r[0, 1] + r[1, 0], 1.0 + 2.0 * r[1, 1] - trace, r[1, 2] + r[2, 1])
    else:
        q = wp.vec4(r[1, 0] - r[0, 1], r[0, 2] + r[2, 0], r[1, 2] + r[2, 1], 1.0 + 2.0 * r[2, 2] - trace)
    return wp.normalize(q)
