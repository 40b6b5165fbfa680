"""The adaptive RANSAC search: vectorized batches replayed in sample order (eqs. 25-27).

Hypotheses are generated and scored in vectorized batches; the batch is then
replayed in sample order, so the bookkeeping (new bests, N after each new best,
the stopping sample) is exactly that of the one-sample-at-a-time loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .config import CELLS_PER_BATCH, FIRST_BATCH, MIN_BATCH, VERIFY_MAX, VERIFY_PER_BATCH
from .hypotheses import local_optimization_step, score_hypotheses, shell_mask, spheres_through_samples
from .sampling import LocalSampler


@dataclass(frozen=True)
class _Search:
    x: np.ndarray | None
    iterations: int
    N: float
    history: np.ndarray
    n_invalid: int
    reason: str
    had_range: bool = False


def adaptive_search(W, sampler, cfg, gen, verifier=None):
    """The adaptive RANSAC loop on the working set W, in replayed vectorized batches."""
    Wsq = np.einsum("ij,ij->i", W, W)
    best = _Best(x=None, score=-np.inf)
    n_valid = n_drawn = n_invalid = 0
    N = math.inf  # the exercise sheet starts with N = infinity
    history: list[tuple[int, float]] = []
    cap = max(MIN_BATCH, CELLS_PER_BATCH // len(W))
    batch = min(FIRST_BATCH, cap) if cfg.minimal_solver == "closed_form" else MIN_BATCH
    had_range = False
    while n_valid < min(N, cfg.max_iterations):
        if n_drawn >= 10 * cfg.max_iterations or (n_drawn >= 2000 and n_valid == 0):
            break
        if best.x is None and verifier is not None and verifier.exhausted:
            break  # every candidate so far failed the verification and its budget is spent
        # Draw and solve a batch; degenerate samples do not count
        idx = sampler.draw(gen, batch)
        X, valid = spheres_through_samples(W[idx], cfg.minimal_solver)
        position = np.flatnonzero(valid)[: cfg.max_iterations - n_valid]  # batch position of each valid sample
        X = X[position]

        # Score hypotheses inside the radius range (the others count but cannot win)
        scores = np.full(len(X), -np.inf)
        ok = (X[:, 3] >= cfg.r_min) & (X[:, 3] <= cfg.r_max)
        if ok.any():
            if isinstance(sampler, LocalSampler):  # inliers lie near the first point: score its block only
                scores[ok] = sampler.blocks.score(W, Wsq, X[ok], idx[position[ok], 0], cfg)
            else:
                scores[ok] = score_hypotheses(W, Wsq, X[ok], cfg.threshold, cfg.scoring)[0]
            had_range = True

        # Replay in sample order: new bests (verified, with LO), N after each (eq. 27), stop at N
        keep, stopped, best, N, events = _replay(X, scores, best, n_valid, N, W, Wsq, sampler, cfg, verifier)
        history += [(n_valid + j + 1, N_j) for j, N_j in events]
        drawn = int(position[keep - 1]) + 1 if stopped else batch  # samples the sequential loop drew
        n_drawn += drawn
        n_invalid += drawn - keep
        n_valid += keep
        batch = _next_batch(N, cfg, n_valid, n_drawn, cap)
    return _Search(
        x=best.x, iterations=n_valid, N=N, n_invalid=n_invalid,
        history=np.array(history, dtype=np.float64).reshape(-1, 2),
        reason=_search_reason(best.x, n_valid, n_drawn, N, cfg, had_range), had_range=had_range,
    )


@dataclass(frozen=True)
class _Best:
    x: np.ndarray | None
    score: float


def _replay(X, scores, best, n_valid, N, W, Wsq, sampler, cfg, verifier=None):
    """Sequential bookkeeping of one batch, exactly as the one-sample-at-a-time loop.

    Walks through the samples that beat the running best in order; each must
    pass the verification to become the new best (a rejected one is skipped,
    the search goes on with the next); each new best is refined by LO (if
    enabled) and sets the required N. Returns the number of valid samples the
    loop used, whether it stopped inside the batch, the best hypothesis, the
    current N and the (position, N) events.
    """
    candidates = np.flatnonzero((scores > best.score) & np.isfinite(scores))
    if verifier is not None and len(candidates):
        # known failures cost no check (looked up for the best-scoring few only)
        top = candidates[np.argsort(-scores[candidates], kind="stable")[: 4 * VERIFY_PER_BATCH]]
        candidates = np.sort(top[~verifier.near_rejected(X[top])])
    if verifier is not None and len(candidates) > VERIFY_PER_BATCH:
        # too many to verify: the running maxima (the new bests of the plain loop) and the
        # best-scoring others, still walked in sample order
        prefix = np.flatnonzero(scores > np.maximum.accumulate(np.concatenate([[best.score], scores]))[:-1])
        top = candidates[np.argsort(-scores[candidates], kind="stable")[:VERIFY_PER_BATCH]]
        candidates = np.array(sorted(set(prefix.tolist()) | set(top.tolist())), dtype=np.int64)  # (np.union1d)
    events = []
    it = n_valid + np.arange(1, len(X) + 1)  # iteration number of each valid sample
    for j in candidates:
        if it[j] > N:
            break  # the loop stopped at sample N, before sample j
        if scores[j] <= best.score:
            continue  # beaten by an earlier (or LO-refined) best meanwhile
        if verifier is not None and not verifier.accepts(X[j], scores[j]):
            continue  # not a sphere cap: the next best may be
        best = _Best(X[j], scores[j])
        N = sampler.required(shell_mask(W, best.x, cfg.threshold), cfg.p)  # (eq. 27)
        events.append((int(j), N))
        if cfg.local_optimization:
            x, score, improved = local_optimization_step(W, Wsq, best.x, best.score, cfg)
            if improved:
                best = _Best(x, score)
                N = min(N, sampler.required(shell_mask(W, x, cfg.threshold), cfg.p))
                events.append((int(j), N))
    keep = int(min(len(X), max(N - n_valid, 0))) if np.isfinite(N) else len(X)
    if events:  # a new best at sample j is always used, even if its N is already exceeded
        keep = max(keep, events[-1][0] + 1)
    stopped = keep < len(X) or (keep > 0 and n_valid + keep >= min(N, cfg.max_iterations))
    return keep, stopped, best, N, events


def _next_batch(N, cfg, n_valid, n_drawn, cap):
    """Enough samples to reach N at the observed validity rate, growing at most geometrically."""
    if cfg.minimal_solver == "ghm":
        return MIN_BATCH
    remaining = min(N, cfg.max_iterations) - n_valid
    rate = max(n_valid / max(n_drawn, 1), 0.05)
    wanted = remaining / rate if np.isfinite(remaining) else math.inf
    return int(min(max(min(wanted, max(n_valid, FIRST_BATCH)), MIN_BATCH), cap))  # (np.clip's result)


def _search_reason(x, n_valid, n_drawn, N, cfg, had_range=True):
    if n_valid == 0:
        return f"every one of the {n_drawn} samples was degenerate (coplanar or repeated points)"
    if x is None and had_range:
        return f"no hypothesis in {n_valid} samples passed the verification (budget {VERIFY_MAX} checks)"
    if x is None:
        return f"no hypothesis had a radius inside [{cfg.r_min:.4g}, {cfg.r_max:.4g}] m in {n_valid} samples"
    if n_valid >= N:
        return f"required N reached ({n_valid} samples, p = {cfg.p})"
    return f"stopped at max_iterations = {cfg.max_iterations} before the required N = {N:.0f} (p not reached)"
