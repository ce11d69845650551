"""Random numbers by position, compiled (numba): draw j of pixel i is a fixed function of (key, i, j), so a
frame's noise is the same whichever thread draws which pixel (docs/physics.md §7).

The stream is SplitMix64 (Steele, Lea & Flood 2014; Java's ``SplittableRandom``): output n of seed ``key``
is mix64(key + (n + 1)·γ) with γ = 0x9E3779B97F4A7C15, a sequence that passes BigCrush. A frame has two
keys. Pixel i's first word is output i of the first key's sequence; its further words come from its own
SplitMix64 sequence, seeded with output i of the second key's (``SplittableRandom.split``): two pixels'
words could only meet if their seeds fell within a few γ-steps of each other (odds ~10⁻⁸ a frame). (Windows
of one sequence, n = i·2³² + j, are not used: that stride has 32 low zero bits, a weak γ whose far normal
tail came out 50 % too heavy.)

On it: uniforms in (0, 1] with 53 random bits, and standard normals by the 256-layer ziggurat (Marsaglia &
Tsang 2000, in the layout of numpy's ``random_standard_normal``: one 64-bit draw for 99.3 % of the normals,
the tail beyond r = 3.654 by Marsaglia's exponential method), exact up to the 52-bit grid of its uniforms.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_GAMMA = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_ONE = np.uint64(1)
_LOW52 = np.uint64((1 << 52) - 1)
_LOW8 = np.uint64(0xFF)


def _ziggurat(layers: int = 256, r: float = 3.6541528853610088, v: float = 4.92867323399e-3):
    """The ziggurat's tables for f(x) = exp(−x²/2) on 52-bit integers (Marsaglia & Tsang 2000, ``zigset``):
    layer i spans [0, x_i), all its points with |x| < x_{i−1} lie under f (``k``); ``w`` maps the integer
    to x, ``f`` is f(x_i). Layer 0 is the base strip plus the tail beyond r (area v each)."""
    scale = float(1 << 52)
    k, w, f = np.zeros(layers, np.uint64), np.zeros(layers), np.zeros(layers)
    x, prev = r, r
    q = v / math.exp(-0.5 * r * r)
    k[0], w[0], w[-1] = int(r / q * scale), q / scale, r / scale
    f[0], f[-1] = 1.0, math.exp(-0.5 * r * r)
    for i in range(layers - 2, 0, -1):
        x = math.sqrt(-2.0 * math.log(v / x + math.exp(-0.5 * x * x)))
        k[i + 1] = int(x / prev * scale)
        prev = x
        f[i], w[i] = math.exp(-0.5 * x * x), x / scale
    k[1] = 0
    return k, w, f, r


_ZK, _ZW, _ZF, _ZR = _ziggurat()


@njit(inline="always")
def splitmix(key, n):
    """Output ``n`` (uint64) of SplitMix64 seeded with ``key``."""
    z = key + (n + _ONE) * _GAMMA
    z = (z ^ (z >> np.uint64(30))) * _M1
    z = (z ^ (z >> np.uint64(27))) * _M2
    return z ^ (z >> np.uint64(31))


@njit(inline="always")
def unit(h):
    """A uniform in (0, 1] from the 53 high bits of ``h``."""
    return (float(np.int64(h >> np.uint64(11))) + 1.0) * 1.1102230246251565e-16   # via int64: a faster cast


@njit(inline="always")
def _layer(h):
    """The ziggurat's step on the 64-bit word ``h``: (x, its layer, negative, x inside the layer's safe
    rectangle — then ±x is the normal, 99.3 %)."""
    idx = h & _LOW8
    h >>= np.uint64(8)
    mag = (h >> _ONE) & _LOW52
    return float(np.int64(mag)) * _ZW[idx], idx, (h & _ONE) == _ONE, mag < _ZK[idx]


@njit(nogil=True)
def _ziggurat_rejected(x, idx, negative, key, n):
    """The ziggurat's rare path (0.7 %, a call of its own that keeps the callers' loops small): the tail
    beyond r (Marsaglia 1964) for layer 0, else the wedge test, and on rejection new words ``n``, … of
    ``key``; (the normal, the next free n)."""
    while True:
        if idx == 0:
            while True:
                xx = -math.log(unit(splitmix(key, n))) / _ZR
                yy = -math.log(unit(splitmix(key, n + _ONE)))
                n += np.uint64(2)
                if yy + yy > xx * xx:
                    return (-(_ZR + xx) if negative else _ZR + xx), n
        u = 1.0 - unit(splitmix(key, n))           # [0, 1)
        n += _ONE
        if (_ZF[idx - 1] - _ZF[idx]) * u + _ZF[idx] < math.exp(-0.5 * x * x):
            return (-x if negative else x), n
        x, idx, negative, inside = _layer(splitmix(key, n))
        n += _ONE
        if inside:
            return (-x if negative else x), n


@njit(inline="always")
def ziggurat(h, key, n):
    """A standard normal from the 64-bit word ``h``, with the words ``n``, ``n + 1``, … of ``key`` drawn
    only when ``h`` falls outside its layer's safe rectangle; (the normal, the next free n)."""
    x, idx, negative, inside = _layer(h)
    if inside:
        return (-x if negative else x), n
    return _ziggurat_rejected(x, idx, negative, key, n)


@njit(inline="always")
def normal(key, n):
    """A standard normal from the words ``n``, ``n + 1``, … of ``key``; (the normal, the next free n)."""
    return ziggurat(splitmix(key, n), key, n + _ONE)


@njit(inline="always")
def own_seed(keys, i):
    """The seed of pixel ``i``'s own sequence: word i of ``keys[1]``'s."""
    return splitmix(keys[1], np.uint64(i))


@njit(inline="always")
def pixel_normal(keys, i):
    """Pixel ``i``'s first normal, from word i of ``keys[0]``'s sequence and, on a ziggurat rejection, the
    words 0, 1, … of its own sequence (:func:`own_seed`); (the normal, the next free word of its own)."""
    x, idx, negative, inside = _layer(splitmix(keys[0], np.uint64(i)))
    if inside:
        return (-x if negative else x), np.uint64(0)
    return _ziggurat_rejected(x, idx, negative, own_seed(keys, i), np.uint64(0))


@njit(nogil=True)
def pixel_normals(keys, first, z, n):
    """:func:`pixel_normal` of the pixels ``first + k``, k < z.size, into z[k] and n[k], in passes that
    vectorize: the words, the ziggurat's step on each (its safe rectangle as a flag, no branch), then the
    few outside it (0.7 %) one by one."""
    count = z.size
    words = np.empty(count, np.uint64)
    key, base = keys[0], np.uint64(first)
    for k in range(count):
        words[k] = splitmix(key, base + np.uint64(k))
    outside = False
    for k in range(count):
        h = words[k]
        idx = h & _LOW8
        mag = (h >> np.uint64(9)) & _LOW52
        x = float(np.int64(mag)) * _ZW[idx]
        z[k] = -x if (h >> np.uint64(8)) & _ONE == _ONE else x
        n[k] = 0
        inside = mag < _ZK[idx]
        outside |= not inside
        if not inside:
            n[k] = 1              # a flag here, the next free word below
    if outside:
        for k in range(count):
            if n[k] != 0:
                x, idx, negative, _ = _layer(words[k])
                z[k], n[k] = _ziggurat_rejected(x, idx, negative, own_seed(keys, first + k), np.uint64(0))


@njit(cache=True, nogil=True)
def normals(keys, first, out):
    """``out[j]`` = the first normal of pixel ``first + j`` (for tests and benches)."""
    pixel_normals(keys, first, out, np.empty(out.size, np.uint64))
