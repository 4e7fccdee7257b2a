"""Heaps on plain arrays: an indexed 4-ary min-heap of (float32 key, int32 item) for the marching
fronts (half the levels of a binary heap for the sift of every pop), each entry one int64 (equal
keys pop the smaller item first: the order is (key, item), not the heap's layout, so the arity
changes no order), and an indexed 4-ary max-heap (item -> position) whose keys only ever decrease, for candidates.
Both only ever see keys decrease, so an entry moves up (min-heap) or down (max-heap).
``check_minheap``/``check_maxheap`` verify the invariants in O(n); the engine calls them after every
operation when its debug switch is on (like scikit-fmm's self test)."""

from __future__ import annotations

import numba as nb
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from . import INLINE, JIT


@nb.njit(**INLINE)
def maxheap_sift_down(hkey, heap, pos, i, n):  # pragma: no cover - compiled
    """Restore the max-heap below position i (after the key there decreased).

    A 4-ary heap with keys stored in heap order (``hkey[i]`` is the key of ``heap[i]``), so a sift
    reads the children's keys from one cache line and the heap is half as deep as a binary one; ``pos[item]`` is the item's position (-1 once popped).
    Ties are broken towards the smaller item so the order is deterministic.
    """
    kv = hkey[i]
    it = heap[i]
    while True:
        c = 4 * i + 1
        if c >= n:
            break
        # the largest of up to four children (one cache line of keys)
        best = c
        for cc in range(c + 1, min(c + 4, n)):
            if hkey[cc] > hkey[best] or (hkey[cc] == hkey[best] and heap[cc] < heap[best]):
                best = cc
        c = best
        if hkey[c] < kv or (hkey[c] == kv and heap[c] > it):
            break
        hkey[i] = hkey[c]
        heap[i] = heap[c]
        pos[heap[i]] = i
        i = c
    hkey[i] = kv
    heap[i] = it
    pos[it] = i


@nb.njit(**JIT)
def maxheap_build(hkey, heap, pos, n):  # pragma: no cover - compiled
    """Heapify the first n entries (items ``heap[i]`` with keys ``hkey[i]``)."""
    for i in range(n):
        pos[heap[i]] = i
    for i in range((n - 2) // 4, -1, -1):
        maxheap_sift_down(hkey, heap, pos, np.int64(i), n)


@nb.njit(**INLINE)
def maxheap_decrease(hkey, heap, pos, item, key, n):  # pragma: no cover - compiled
    """Lower the key of ``item`` (if it is still in the heap) to ``key``."""
    i = np.int64(pos[item])
    if i >= 0:
        hkey[i] = key
        maxheap_sift_down(hkey, heap, pos, i, n)


@nb.njit(**INLINE)
def maxheap_pop(hkey, heap, pos, n):  # pragma: no cover - compiled
    """Remove the top item; returns the new size."""
    pos[heap[0]] = -1
    n -= 1
    if n > 0:
        hkey[0] = hkey[n]
        heap[0] = heap[n]
        pos[heap[0]] = 0
        maxheap_sift_down(hkey, heap, pos, np.int64(0), n)
    return n


@intrinsic
def f32_bits(typingctx, x):  # pragma: no cover - compiled
    """The bits of a float32 as a (non-negative) int64."""
    if x != types.float32:
        return None

    def codegen(context, builder, signature, args):
        return builder.zext(builder.bitcast(args[0], ir.IntType(32)), ir.IntType(64))

    return types.int64(types.float32), codegen


@intrinsic
def bits_f32(typingctx, x):  # pragma: no cover - compiled
    """The float32 whose bits are the low 32 bits of an int64."""
    if x != types.int64:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(builder.trunc(args[0], ir.IntType(32)), ir.FloatType())

    return types.float32(types.int64), codegen


@intrinsic
def f64_bits(typingctx, x):  # pragma: no cover - compiled
    """The bits of a float64 as a uint64."""
    if x != types.float64:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return types.uint64(types.float64), codegen


ITEM_MASK = np.int64(0xFFFFFFFF)


@nb.njit(**INLINE)
def iheap_push(hkv, hpos, n, key, item):  # pragma: no cover - compiled
    """Insert ``item`` into an indexed min-heap, or lower its key if it is already there.

    An entry is one int64: the bits of its float32 key (>= 0) above the item (< 2^31), so that
    integer order is the order (key, item) and a sift reads one array. ``hpos[item]`` is the
    item's position in the heap or -1. Keys only ever decrease, so the entry only moves up. The
    arrays hold one entry per possible item (no growth, so callers never rebind them: rebinding
    arrays in a hot loop costs atomic reference counting). Returns the new size.
    """
    i = np.int64(hpos[item])
    if i < 0:
        i = n
        n += 1
    e = (f32_bits(key) << 32) | np.int64(item)
    while i > 0:
        p = (i - 1) >> 2
        ep = hkv[p]
        if ep < e:
            break
        hkv[i] = ep
        hpos[ep & ITEM_MASK] = i
        i = p
    hkv[i] = e
    hpos[item] = i
    return n


@nb.njit(**INLINE)
def iheap_pop(hkv, hpos, n):  # pragma: no cover - compiled
    """Pop the smallest entry of an indexed min-heap; returns (key, item, n - 1)."""
    e0 = hkv[0]
    item = np.int32(e0 & ITEM_MASK)
    hpos[item] = -1
    n -= 1
    if n > 0:
        last = hkv[n]
        i = np.int64(0)
        while True:
            c = 4 * i + 1
            if c >= n:
                break
            ec = hkv[c]  # the smallest of up to four children
            for cc in range(c + 1, min(c + 4, n)):
                if hkv[cc] < ec:
                    c = cc
                    ec = hkv[cc]
            if ec > last:
                break
            hkv[i] = ec
            hpos[ec & ITEM_MASK] = i
            i = c
        hkv[i] = last
        hpos[last & ITEM_MASK] = i
    return bits_f32(e0 >> 32), item, n


@nb.njit(**JIT)
def check_minheap(hkv, hpos, n):  # pragma: no cover - compiled
    """True when the first n entries form a 4-ary min-heap whose positions ``hpos`` agree."""
    for i in range(n):
        if hpos[hkv[i] & ITEM_MASK] != i:
            return False
        if i > 0 and hkv[(i - 1) >> 2] > hkv[i]:
            return False
    return True


@nb.njit(**JIT)
def check_maxheap(hkey, heap, pos, n):  # pragma: no cover - compiled
    """True when the first n entries form a 4-ary max-heap whose positions ``pos`` agree."""
    for i in range(n):
        if pos[heap[i]] != i:
            return False
        if i > 0 and hkey[(i - 1) >> 2] < hkey[i]:
            return False
    return True
