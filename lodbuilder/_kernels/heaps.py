"""Binary heaps on plain arrays: an indexed min-heap of (float32 key, int32 item) for the marching
fronts, and an indexed max-heap (item -> position) whose keys only ever decrease, for candidates.
Both only ever see keys decrease, so an entry moves up (min-heap) or down (max-heap)."""

from __future__ import annotations

import numba as nb
import numpy as np

from . import JIT


@nb.njit(**JIT)
def maxheap_sift_down(heap, pos, key, i, n):  # pragma: no cover - compiled
    """Restore the max-heap below position i (after the key of heap[i] decreased).

    Ties are broken towards the smaller item so the order is deterministic.
    """
    it = heap[i]
    kv = key[it]
    while True:
        c = 2 * i + 1
        if c >= n:
            break
        if c + 1 < n:
            a = heap[c]
            b = heap[c + 1]
            if key[b] > key[a] or (key[b] == key[a] and b < a):
                c += 1
        ch = heap[c]
        if key[ch] < kv or (key[ch] == kv and ch > it):
            break
        heap[i] = ch
        pos[ch] = i
        i = c
    heap[i] = it
    pos[it] = i


@nb.njit(**JIT)
def maxheap_build(heap, pos, key, n):  # pragma: no cover - compiled
    for i in range(n):
        pos[heap[i]] = i
    for i in range(n // 2 - 1, -1, -1):
        maxheap_sift_down(heap, pos, key, i, n)


@nb.njit(**JIT)
def maxheap_pop(heap, pos, key, n):  # pragma: no cover - compiled
    """Remove the top item; returns the new size."""
    top = heap[0]
    pos[top] = -1
    n -= 1
    if n > 0:
        heap[0] = heap[n]
        pos[heap[0]] = 0
        maxheap_sift_down(heap, pos, key, 0, n)
    return n


@nb.njit(**JIT)
def iheap_push(hk, hv, hpos, n, key, item):  # pragma: no cover - compiled
    """Insert ``item`` into an indexed min-heap, or lower its key if it is already there.

    ``hpos[item]`` is the item's position in the heap or -1. Keys only ever decrease, so the entry
    only moves up. Returns (hk, hv, n) (the arrays grow when full).
    """
    i = hpos[item]
    if i < 0:
        if n == hk.shape[0]:
            nk = np.empty(2 * n, hk.dtype)
            nv = np.empty(2 * n, hv.dtype)
            nk[:n] = hk
            nv[:n] = hv
            hk, hv = nk, nv
        i = n
        n += 1
    while i > 0:
        p = (i - 1) >> 1
        if hk[p] <= key:
            break
        hk[i] = hk[p]
        hv[i] = hv[p]
        hpos[hv[i]] = i
        i = p
    hk[i] = key
    hv[i] = item
    hpos[item] = i
    return hk, hv, n


@nb.njit(**JIT)
def iheap_pop(hk, hv, hpos, n):  # pragma: no cover - compiled
    """Pop the smallest entry of an indexed min-heap; returns (key, item, n - 1)."""
    key = hk[0]
    item = hv[0]
    hpos[item] = -1
    n -= 1
    if n > 0:
        lk = hk[n]
        lv = hv[n]
        i = 0
        while True:
            c = 2 * i + 1
            if c >= n:
                break
            if c + 1 < n and hk[c + 1] < hk[c]:
                c += 1
            if hk[c] >= lk:
                break
            hk[i] = hk[c]
            hv[i] = hv[c]
            hpos[hv[i]] = i
            i = c
        hk[i] = lk
        hv[i] = lv
        hpos[lv] = i
    return key, item, n
