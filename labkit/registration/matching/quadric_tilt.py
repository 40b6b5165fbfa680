"""The tilt covariance of quadric normals, row by row (the compiled kernel of ``Geometry.tilt``).

ICP asks for the tilt of the target normals at every accepted pair in every iteration (eq. 5.12b); with
``surface='quadric'`` that is T C T^T per row from the stored frames and slope covariances. numpy forms it by a
gather of each store and a three-operand einsum; one pass here gives the same numbers.
"""

from __future__ import annotations

import numpy as np

from ...core.jit import compiled, have_numba


def quadric_tilt(store, slot, pos, get):
    """Tilt covariance (m, 3, 3) of the quadric normals at the leaf positions ``pos``, from the geometry cache's
    ``store`` of frames and slope covariances, its ``slot`` of each position, and ``get(name, pos)``, its gather."""
    if have_numba() and "frame" in store:  # one compiled pass over the rows (the same numbers)
        return compiled(quadric_tilt_rows)(store["frame"], store["slope"], slot, pos)
    T = get("frame", pos)[:, :, [2, 1]]  # tangents t1 (u), t2 (v)
    vd, cde, ve = get("slope", pos).T
    C = np.stack([np.stack([vd, cde], -1), np.stack([cde, ve], -1)], -2)
    return np.einsum("mia,mab,mjb->mij", T, C, T)


def quadric_tilt_rows(frame, slope, slot, pos):  # pragma: no cover - compiled
    """:func:`quadric_tilt` from the stored frames and slope covariances: T C T^T of each row with T = (t1, t2)
    (columns 2 and 1 of the frame), C = [[vd, cde], [cde, ve]], rows taken as np.take takes them (a slot of -1
    is the buffer's last row), each entry's four products ((t_ia c_ab) t_jb) added in einsum's order from zero."""
    m = pos.shape[0]
    n = frame.shape[0]
    out = np.empty((m, 3, 3))
    C = np.empty((2, 2))
    T = np.empty((3, 2))
    for r in range(m):
        s = slot[pos[r]]
        if s < 0:
            s += n
        C[0, 0], C[0, 1], C[1, 0], C[1, 1] = slope[s, 0], slope[s, 1], slope[s, 1], slope[s, 2]
        for i in range(3):
            T[i, 0], T[i, 1] = frame[s, i, 2], frame[s, i, 1]
        for i in range(3):
            for j in range(3):
                acc = 0.0
                for a in range(2):
                    for b in range(2):
                        acc += (T[i, a] * C[a, b]) * T[j, b]
                out[r, i, j] = acc
    return out
