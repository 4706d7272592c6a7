"""The correlation kernel in AVX-512 (psadbw on 64 bytes), for CPUs that have AVX-512BW.

Same integers as kernel._sad, computed another way round: the portable kernel runs over the offsets k (one
window column at a time, the scores in uint16 lanes); this one loads, per window row, the 64 band bytes at
offset k, which hold the windows of the offsets k, k + L, ... (L = 16, 32 or 64 lanes per window row, the
fovea row repeated in each, the band bytes past w masked to zero), and sums each lane group with one psadbw.
Up to eight vertical shifts v .. v + 7 go together, so that a band row is loaded once for all of them (two
shifts per pass took 2.5 ms at 3840/31/V33, four 1.8 ms, eight 1.4 ms: the loads were the limit). The direction
plane is compared on the circle as |int8(b - f)| = |(b - (f ^ 0x80)) - 128|: one subtraction and one psadbw
against 128. With support weights, the differences are multiplied by the weights (pmaddubsw, pmaddwd).

The band is copied into rows of an odd number of cache lines (a row stride of 2048 bytes put every row of
the window into the same few L1 sets and halved the speed) with 128 spare bytes, so no load leaves it."""

from __future__ import annotations

import os

import numba
import numpy as np
from llvmlite import binding, ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["AVAILABLE", "MAX_WINDOW", "MAX_WEIGHT", "sad"]

MAX_WINDOW = 64  # one window row must fit in the 64 bytes of a vector
MAX_WEIGHT = 64  # pmaddubsw takes signed bytes and saturates at 2 * 255 * weight > 32767

_FEATURES = binding.get_host_cpu_features()
# numba compiles for the host CPU unless NUMBA_CPU_NAME names another (portable caches): then no AVX-512
AVAILABLE = (all(_FEATURES.get(f, False) for f in ("avx512f", "avx512bw"))
             and os.environ.get("NUMBA_CPU_NAME", "host") == "host")

_I1, _I8, _I16, _I32, _I64 = (ir.IntType(n) for n in (1, 8, 16, 32, 64))
_B64 = ir.VectorType(_I8, 64)
_W32 = ir.VectorType(_I16, 32)
_D16 = ir.VectorType(_I32, 16)
_Q8 = ir.VectorType(_I64, 8)

# cfg bits: 1 circular (always: the linear comparison is the paper's, left to the portable kernel), 2 weighted,
# 4 L = 32, 8 L = 64 (else 16); 16, 32, 64: 2, 4, 8 vertical shifts (else 1). Each variant costs compile time.
_CFGS = [c for c in range(128) if c & 1 and not (c & 4 and c & 8) and bin(c & 112).count("1") <= 1]
_SHIFTS = {0: 1, 16: 2, 32: 4, 64: 8}


def _const(n: int) -> ir.Constant:
    return ir.Constant(_I64, n)


def _declare(builder, name, ret, args):
    return cgutils.get_or_insert_function(builder.module, ir.FunctionType(ret, args), name)


def _emit(cfg: int, builder, pb, ps, rs, pf, pw, w, po, os_):
    """S(v + r, k + p L) for p < 64 / L and r < the cfg's number of shifts, stored at po + r os_ + 8 p L."""
    circular, weighted = bool(cfg & 1), bool(cfg & 2)
    lanes = 32 if cfg & 4 else 64 if cfg & 8 else 16
    nv = _SHIFTS[cfg & 112]
    psad = _declare(builder, "llvm.x86.avx512.psad.bw.512", _Q8, [_B64, _B64])
    pmub = _declare(builder, "llvm.x86.avx512.pmaddubs.w.512", _W32, [_B64, _B64])
    pmwd = _declare(builder, "llvm.x86.avx512.pmaddw.d.512", _D16, [_W32, _W32])
    absb = _declare(builder, "llvm.abs.v64i8", _B64, [_B64, _I1])
    umax = _declare(builder, "llvm.umax.v64i8", _B64, [_B64, _B64])
    umin = _declare(builder, "llvm.umin.v64i8", _B64, [_B64, _B64])
    ones = ir.Constant(_W32, [1] * 32)
    half = ir.Constant(_B64, [128] * 64)
    lane = ir.Constant(_B64, [b % lanes for b in range(64)])
    wsplat = builder.shuffle_vector(
        builder.insert_element(ir.Constant(_B64, ir.Undefined), builder.trunc(w, _I8), ir.Constant(_I32, 0)),
        ir.Constant(_B64, ir.Undefined), ir.Constant(ir.VectorType(_I32, 64), [0] * 64))
    mask = builder.sext(builder.icmp_unsigned("<", lane, wsplat), _B64)
    fplane = builder.mul(w, _const(64))

    def load(addr):
        return builder.load(builder.inttoptr(addr, _B64.as_pointer()), align=1)

    def band_row(i, plane):
        b = load(builder.add(builder.add(pb, builder.mul(rs, i)), builder.mul(ps, _const(plane))))
        return b if weighted else builder.and_(b, mask)  # weighted: the zero weights past w mask

    def term(b, f, wv, circ):
        if not weighted:
            if circ:
                return builder.bitcast(builder.call(psad, [builder.sub(b, f), half]), _D16)
            return builder.bitcast(builder.call(psad, [b, f]), _D16)
        if circ:
            d = builder.call(absb, [builder.sub(b, f), ir.Constant(_I1, 0)])
        else:
            d = builder.sub(builder.call(umax, [b, f]), builder.call(umin, [b, f]))
        return builder.call(pmwd, [builder.call(pmub, [d, wv]), ones])

    accs = [cgutils.alloca_once_value(builder, ir.Constant(_D16, None)) for _ in range(nv)]
    for p in range(3):  # a plane at a time: nv accumulators and nv - 1 carried band rows stay in registers
        circ = circular and p == 2
        # carried[j]: band row v + i + j (j < nv - 1), loaded at an earlier i: each row is loaded once
        carried = [cgutils.alloca_once_value(builder, band_row(_const(j), p)) for j in range(nv - 1)]
        with cgutils.for_range(builder, w) as loop:
            i = loop.index
            acc = [builder.load(a) for a in accs]
            wv = load(builder.add(pw, builder.mul(i, _const(64)))) if weighted else None
            f = load(builder.add(builder.add(pf, builder.mul(i, _const(64))), builder.mul(fplane, _const(p))))
            rows = [builder.load(c) for c in carried] + [band_row(builder.add(i, _const(nv - 1)), p)]
            for r in range(nv):
                acc[r] = builder.add(acc[r], term(rows[r], f, wv, circ))
            for j in range(nv - 1):
                builder.store(rows[j + 1], carried[j])
            for a, x in zip(accs, acc):
                builder.store(x, a)
    q = lanes // 4  # 32-bit lanes per offset (psadbw's 64-bit sums have zero upper halves)
    red = _declare(builder, f"llvm.vector.reduce.add.v{q}i32", _I32, [ir.VectorType(_I32, q)])
    for r in range(nv):
        acc = builder.load(accs[r])
        out = builder.inttoptr(builder.add(po, builder.mul(os_, _const(r))), _I64.as_pointer())
        for p in range(64 // lanes):
            part = builder.shuffle_vector(acc, ir.Constant(_D16, ir.Undefined),
                                          ir.Constant(ir.VectorType(_I32, q), list(range(p * q, p * q + q))))
            builder.store(builder.zext(builder.call(red, [part]), _I64), builder.gep(out, [_const(p * lanes)]))


@intrinsic
def _block(typingctx, cfg, pb, ps, rs, pf, pw, w, po, os_):
    """One call of _emit, chosen by cfg at run time (a switch: cfg is the same for the whole band)."""
    sig = types.int64(*([types.int64] * 9))

    def codegen(context, builder, signature, args):
        done = builder.append_basic_block("sad.done")
        switch = builder.switch(args[0], done)
        for c in _CFGS:
            block = builder.append_basic_block(f"sad.cfg{c}")
            switch.add_case(_const(c), block)
            builder.position_at_end(block)
            _emit(c, builder, *args[1:])
            builder.branch(done)
        builder.position_at_end(done)
        return _const(0)

    return sig, codegen


@numba.njit(cache=True, nogil=True)
def _drive(cfg, bpad, fpad, wpad, w, lanes, nv, k0, n, out):
    pb = np.int64(bpad.ctypes.data)
    ps, rs = np.int64(bpad.strides[0]), np.int64(bpad.strides[1])
    pf, pw = np.int64(fpad.ctypes.data), np.int64(wpad.ctypes.data)
    os_ = np.int64(out.strides[0])
    v = 0
    while v < nv:  # eight vertical shifts at a time, then four, two, one
        step = 8 if v + 8 <= nv else 4 if v + 4 <= nv else 2 if v + 2 <= nv else 1
        c = cfg + (8 * step if step > 1 else 0)
        base = pb + v * rs + k0
        po = np.int64(out[v].ctypes.data)
        for kb in range(0, n, 64):  # block kb: the loads at kb + t cover kb + t + p * lanes
            for t in range(min(lanes, n - kb)):
                k = kb + t
                _block(c, base + k, ps, rs, pf, pw, w, po + 8 * k, os_)
        v += step


def sad(fovea: np.ndarray, band: np.ndarray, k0: int, k1: int, weights: np.ndarray | None) -> np.ndarray:
    """kernel.sad's S(v, k) with the circular direction comparison, k0 <= k < k1, for w <= MAX_WINDOW and
    weights <= MAX_WEIGHT (kernel.sad checks the arguments)."""
    c, w, _ = fovea.shape
    lanes = 16 if w <= 16 else 32 if w <= 32 else 64
    rows, width = band.shape[1], band.shape[2]
    stride = 64 * (((width + 128 + 63) // 64) | 1)
    bpad = np.empty((c, rows, stride), np.uint8)
    bpad[:, :, width:] = 0
    bpad[:, :, :width] = band
    fpad = np.zeros((c, w, 64), np.uint8)
    wpad = np.zeros((w, 64), np.uint8)
    for p in range(64 // lanes):
        fpad[:, :, p * lanes : p * lanes + w] = fovea
        if weights is not None:
            wpad[:, p * lanes : p * lanes + w] = weights
    if weights is None:
        fpad[2] ^= 0x80
    nv, n = rows - w + 1, k1 - k0
    out = np.empty((nv, n + 64), np.int64)
    cfg = 1 + 2 * (weights is not None) + {16: 0, 32: 4, 64: 8}[lanes]
    _drive(cfg, bpad, fpad, wpad, w, lanes, nv, k0, n, out)
    return out[:, :n]
