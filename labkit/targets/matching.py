"""Correspondences between sphere targets of two scans from the distances between them (notebook 11, section 7).

Distances between targets do not change under a rigid transformation. A candidate correspondence is a pair
(i in A, a in B); two candidates (i, a) and (j, b) agree when |d_A(i, j) - d_B(a, b)| is below a tolerance
built from the centres' covariances (plus a floor that lets a target moved by a few centimetres through, so
that the adjustment's test finds and names it). The correspondences are the largest set of mutually agreeing
candidates (a clique of the agreement graph), grown greedily from every seed; no IDs are needed and targets
seen in one scan only, or spheres that are not targets, simply stay unmatched.
"""

from __future__ import annotations

import numpy as np

_K_SIGMA = 5.0  # distances agree within this many standard deviations (plus the floor)


def _distances(X):
    return np.sqrt(((X[:, None, :] - X[None, :, :]) ** 2).sum(axis=-1))


def agreement(A, CA, B, CB, floor):
    """Boolean (m n, m n) agreement of candidate pairs (i, a), (j, b), index i * n + a."""
    m, n = len(A), len(B)
    vA, vB = np.trace(CA, axis1=1, axis2=2) / 3, np.trace(CB, axis1=1, axis2=2) / 3
    diff = np.abs(_distances(A)[:, None, :, None] - _distances(B)[None, :, None, :])  # [i, a, j, b]
    var = vA[:, None, None, None] + vA[None, None, :, None] + vB[None, :, None, None] + vB[None, None, None, :]
    ok = diff <= _K_SIGMA * np.sqrt(var) + floor
    ok &= ~np.eye(m, dtype=bool)[:, None, :, None]
    ok &= ~np.eye(n, dtype=bool)[None, :, None, :]
    return ok.reshape(m * n, m * n)


def largest_clique(G):
    """Largest set of mutually agreeing candidates found by greedy growth from every seed (vertex indices)."""
    deg = G.sum(axis=1)
    best = np.zeros(0, int)
    for seed in np.argsort(-deg):
        if deg[seed] + 1 <= len(best):
            break  # no seed of lower degree can give a larger clique
        clique, cand = [seed], G[seed].copy()
        while cand.any():
            idx = np.flatnonzero(cand)
            # the candidate that keeps most of the others in play
            nxt = idx[np.argmax(G[np.ix_(idx, idx)].sum(axis=1))]
            clique.append(nxt)
            cand &= G[nxt]
        if len(clique) > len(best):
            best = np.array(clique)
    return best


def match_targets(A, CA, B, CB, floor=0.05):
    """Pairs (i, a) of corresponding targets in A (m, 3) and B (n, 3); shape (k, 2), sorted by i.

    Fewer than two agreeing candidates give no pairs (one pair alone says nothing).
    """
    if len(A) < 2 or len(B) < 2:
        return np.zeros((0, 2), int)
    G = agreement(A, CA, B, CB, floor)
    clique = largest_clique(G)
    if len(clique) < 2:
        return np.zeros((0, 2), int)
    pairs = np.column_stack(np.divmod(clique, len(B)))
    return pairs[np.argsort(pairs[:, 0])]
