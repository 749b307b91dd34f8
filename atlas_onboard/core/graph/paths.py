"""Path finding over the edge arrays and the evaluation plan it gives.

The paper's broad phase is a breadth-first search from the root (``bfs``): a vertex's parents are
its neighbours exactly one level lower. Beyond the paper, ``dijkstra`` takes each edge's variance
(sigma^2) as its length: a vertex's parents are its neighbours with a better chain to the root.
A :class:`Plan` turns either into the list of candidates (edge row, direction, parent, child) that
the pose phase fuses, sorted so that each stage is a contiguous slice.
"""

from __future__ import annotations

import heapq
import itertools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from atlas_onboard.core import covariance, fusion
from atlas_onboard.core.graph.edges import EdgeStore

PATHS = ("bfs", "dijkstra")


def bfs(a: NDArray[np.intp], b: NDArray[np.intp], root: int, n: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Breadth-first search over edges ``a[i] - b[i]`` among ``n`` vertices, one level at a time.

    Returns the visiting order and the level of every vertex (-1: not reached). The order is a
    queue's: a level's vertices in the order of the parent that found them first, and those of
    one parent in the order of the world file, so it is deterministic.
    """
    level = np.full(n, -1, dtype=np.intp)
    rank = np.full(n, n, dtype=np.intp)
    level[root], rank[root] = 0, 0
    order = [np.array([root], dtype=np.intp)]
    found, depth = 1, 0
    # Only the edges with an end not yet reached can still find a vertex: each level's search runs
    # over those, so the whole search costs about twice the edges, whatever the depth.
    open_ = np.arange(a.size)
    while True:
        la, lb = level[a[open_]], level[b[open_]]
        down = (la == depth) & (lb < 0)
        up = (lb == depth) & (la < 0)
        child = np.concatenate((b[open_[down]], a[open_[up]]))
        if child.size == 0:
            break
        parent = np.concatenate((a[open_[down]], b[open_[up]]))
        first = np.full(n, n, dtype=np.intp)
        np.minimum.at(first, child, rank[parent])
        new = np.unique(child)
        new = new[np.lexsort((new, first[new]))]
        depth += 1
        level[new] = depth
        rank[new] = np.arange(found, found + new.size)
        found += new.size
        order.append(new)
        open_ = open_[(la < 0) | (lb < 0)]
    return np.concatenate(order), level


def dijkstra(
    a: NDArray[np.intp], b: NDArray[np.intp], sigma: NDArray[np.float64], root: int, n: int
) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """Shortest chains from ``root`` with each edge's variance as its length. Variances add along a
    chain of independent transforms, so the distance of a vertex is the variance of its best chain:
    the paper's future work ("use the standard deviation information of the graph as distance ...
    Dijkstra"). Returns the visiting order and the distances (inf for vertices not reached)."""
    best: dict[tuple[int, int], float] = {}
    for u, v, s in zip(a.tolist(), b.tolist(), (sigma**2).tolist(), strict=True):
        k = (min(u, v), max(u, v))
        best[k] = min(best.get(k, np.inf), s)
    adj: list[list[tuple[int, float]]] = [[] for _ in range(n)]
    for (u, v), w in best.items():
        adj[u].append((v, w))
        adj[v].append((u, w))
    dist = np.full(n, np.inf)
    dist[root] = 0.0
    order: list[int] = []
    heap = [(0.0, root)]
    done: set[int] = set()
    while heap:
        d, v = heapq.heappop(heap)
        if v in done:
            continue
        done.add(v)
        order.append(v)
        for u, w in adj[v]:
            nd = d + w
            if u not in done and nd < dist[u]:
                dist[u] = nd
                heapq.heappush(heap, (nd, u))
    return np.array(order, dtype=np.intp), dist


@dataclass(frozen=True, slots=True)
class Plan:
    """What an evaluation does, given which edges exist (not their values): the broad phase's order
    and levels, and every candidate (edge row, direction, parent, child) sorted by stage, child and
    parent, with each stage's run. With BFS paths it is kept until an edge appears or goes.

    Arrays: ``order`` (reached vertices in visiting order), ``level`` and ``stage_of`` (per vertex;
    level -1: not reached), and per candidate ``row`` (edge row), ``direction`` (0: the edge as
    given, 1: its inverse), ``parent``, ``child``.
    """

    order: NDArray[np.intp]
    level: NDArray[np.intp]
    stage_of: NDArray[np.intp]
    row: NDArray[np.intp]
    direction: NDArray[np.intp]
    parent: NDArray[np.intp]
    child: NDArray[np.intp]
    stages: tuple[slice, ...]
    runs: tuple[tuple[fusion.Runs, fusion.Runs], ...]  # per stage: runs of each child, of each (child, parent)
    from_root: tuple[bool, ...]  # per stage: every parent is the root (exact: identity, no covariance)
    goal_is_parent: bool  # the goal (if any) is the parent of a candidate (left out of a goal's plan)


class Planner:
    """Makes plans, and keeps BFS plans while the shape of the graph (:attr:`EdgeStore.version`)
    stays: most evaluations of a running node only refresh edges. Dijkstra's plan depends on the
    sigmas, so it is made anew each time."""

    def __init__(self, n_vertices: int, path: str) -> None:
        self.n = n_vertices
        self.path = path
        self._kept: dict[tuple[int, int, int | None], Plan] = {}

    def clear(self) -> None:
        """Forget the kept plans: the next evaluation plans anew, as after an edge appears or goes."""
        self._kept.clear()

    def plan(self, store: EdgeStore, slots: NDArray[np.intp], root: int, goal: int | None) -> Plan:
        """The plan of an evaluation from ``root`` over the live edges ``slots``; with ``goal``, only
        the candidates of vertices of a lower stage than ``goal``, and of ``goal`` itself."""
        key = (store.version, root, goal)
        kept = self._kept.get(key) if self.path == "bfs" else None
        if kept is not None:
            return kept
        plan = self._make(store, slots, root, goal)
        if self.path == "bfs":
            if len(self._kept) >= 8:  # old shapes are never asked for again
                self._kept.clear()
            self._kept[key] = plan
        return plan

    def _make(self, store: EdgeStore, slots: NDArray[np.intp], root: int, goal: int | None) -> Plan:
        n = self.n
        a, b = store.a[slots], store.b[slots]
        order_arr, level = bfs(a, b, root, n)
        la, lb = level[a], level[b]
        reached = (la >= 0) & (lb >= 0)
        if self.path == "dijkstra":
            order_arr, dist = dijkstra(a, b, store.sigma[slots], root, n)
            down = reached & (dist[a] < dist[b])  # a is b's parent: the edge is walked as given
            up = reached & (dist[b] < dist[a])  # b is a's parent: the edge is walked backwards
        else:
            down = reached & (lb == la + 1)
            up = reached & (la == lb + 1)
        rank = np.full(n, n, dtype=np.intp)
        rank[order_arr] = np.arange(order_arr.size)
        row = np.concatenate((slots[down], slots[up]))
        direction = np.concatenate((np.zeros(down.sum(), dtype=np.intp), np.ones(up.sum(), dtype=np.intp)))
        parent = np.concatenate((a[down], b[up]))
        child = np.concatenate((b[down], a[up]))
        stage_of = _stages(level, parent, child, n) if self.path == "dijkstra" else np.maximum(level, 0)
        goal_is_parent = False
        if goal is not None and level[goal] >= 0:
            goal_is_parent = bool((parent == goal).any())
            wanted = (stage_of[child] < stage_of[goal]) | (child == goal)
            row, direction, parent, child = row[wanted], direction[wanted], parent[wanted], child[wanted]
        # Sorted by stage, then child (evaluation order), then parent, then edge.
        sort = np.lexsort((row, parent, rank[child], stage_of[child]))
        row, direction, parent, child = row[sort], direction[sort], parent[sort], child[sort]
        cuts = [0, *(np.flatnonzero(np.diff(stage_of[child])) + 1).tolist(), row.size] if row.size else []
        stages = tuple(slice(i, j) for i, j in itertools.pairwise(cuts))
        runs = tuple(covariance.runs_by_parent(child[sel], parent[sel]) for sel in stages)
        from_root = tuple(bool((parent[sel] == root).all()) for sel in stages)
        return Plan(order_arr, level, stage_of, row, direction, parent, child, stages, runs, from_root, goal_is_parent)


def _stages(level: NDArray[np.intp], parent: NDArray[np.intp], child: NDArray[np.intp], n: int) -> NDArray[np.intp]:
    """A vertex's stage is one more than its deepest parent's, so that a whole stage can be
    composed and fused in one batched call (for BFS the stage is the level)."""
    stage_of = np.zeros(n, dtype=np.intp)
    while True:
        nxt = np.zeros(n, dtype=np.intp)
        np.maximum.at(nxt, child, stage_of[parent] + 1)
        if np.array_equal(nxt, stage_of):
            return stage_of
        stage_of = nxt
