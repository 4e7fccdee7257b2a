"""Binary heaps on plain arrays: a lazy min-heap of (float32 key, int32 item) for the marching fronts,
and an indexed max-heap (item -> position) whose keys only ever decrease, for candidates."""

from __future__ import annotations

import numba as nb
import numpy as np

from . import JIT


@nb.njit(**JIT)
def minheap_push(hk, hv, n, key, item):  # pragma: no cover - compiled
    """Push onto a lazy min-heap of size n; returns (hk, hv, n) (arrays grow when full)."""
    if n == hk.shape[0]:
        nk = np.empty(2 * n, hk.dtype)
        nv = np.empty(2 * n, hv.dtype)
        nk[:n] = hk
        nv[:n] = hv
        hk, hv = nk, nv
    i = n
    while i > 0:
        p = (i - 1) >> 1
        if hk[p] <= key:
            break
        hk[i] = hk[p]
        hv[i] = hv[p]
        i = p
    hk[i] = key
    hv[i] = item
    return hk, hv, n + 1


@nb.njit(**JIT)
def minheap_pop(hk, hv, n):  # pragma: no cover - compiled
    """Pop the smallest entry; returns (key, item, n - 1). n must be > 0."""
    key = hk[0]
    item = hv[0]
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
            i = c
        hk[i] = lk
        hv[i] = lv
    return key, item, n


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
