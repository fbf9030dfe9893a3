"""The VelociRoACH sim's 1 kHz loop compiled with numba (the ``speed`` extra), when installed.

What it runs is the inlined loop of ``VelociRoachSim._advance`` (the firmware's leg-velocity
PID, the battery and the motor currents, ``mj_step``) and the 120 Hz mocap model (the
terrain wrap, the sample's dropout and noise: ``_wrap`` and ``_mocap_sample``) for as long as
nothing but the PID runs (not past a tick on which the watchdog trips, not with a towed
payload): the same operations in the same order on the same doubles, the noise drawn from the
backend's own numpy Generator with numpy's algorithms, so the floats are identical
(tests/velociroach/test_sim.py). ``mj_step`` is called through its C entry point in the
MuJoCo library the bindings loaded (``MjModel._address``/``MjData._address``), and the
Generator's bit generator through its ctypes function pointers, so a control period costs
one call from Python. Without numba :func:`kernel` is None and the backend runs the same
loop in Python.

Why: at 1 ms physics steps the Python loop (about 40 float operations and a binding call
per step) cost as much as the physics in ``hil bench sim``; handing back to Python for each
of the 12 mocap samples of a period cost about 40 us of the period's 750 (docs/platform.md,
"`hil bench sim`").
"""

from __future__ import annotations

import ctypes
import functools
import glob
import math
import os
from typing import Any

try:
    import numba
    from llvmlite import ir
    from numba import types
    from numba.extending import intrinsic

    # numpy's ziggurat tables for the standard normal, as numba's own Generator support copies them
    from numba.np.random._constants import fi_double, ki_double, wi_double, ziggurat_nor_inv_r, ziggurat_nor_r
except ImportError:  # the speed extra is not installed: the backend's Python loop runs
    numba = None



def _mj_step_address() -> int:
    """The address of ``mj_step`` in the MuJoCo library the Python bindings use."""
    import mujoco

    libs = sorted(glob.glob(os.path.join(os.path.dirname(mujoco.__file__), "libmujoco.so*")))
    if not libs:
        raise OSError("no libmujoco.so beside the mujoco package")
    lib = ctypes.CDLL(libs[0])  # already loaded by the bindings: the same handle
    return ctypes.cast(lib.mj_step, ctypes.c_void_p).value


@functools.cache
def kernel() -> tuple[Any, int] | None:
    """``(run, mj_step address)``, or None without numba (compiled once, cached on disk)."""
    if numba is None:
        return None
    return run, _mj_step_address()


if numba is not None:

    @intrinsic
    def _mj_step(typingctx, fn, m, d):
        """Call ``void mj_step(const mjModel*, mjData*)`` at address ``fn`` (integers: a
        pointer held as an argument, not a global, keeps the function cacheable)."""
        sig = types.void(types.intp, types.intp, types.intp)

        def codegen(context, builder, signature, args):
            vp = ir.IntType(8).as_pointer()
            fnty = ir.FunctionType(ir.VoidType(), [vp, vp])
            f = builder.inttoptr(args[0], fnty.as_pointer())
            builder.call(f, [builder.inttoptr(args[1], vp), builder.inttoptr(args[2], vp)])
            return context.get_dummy_value()

        return sig, codegen

    def _call_state_fn(builder, args, ret):
        vp = ir.IntType(8).as_pointer()
        f = builder.inttoptr(args[0], ir.FunctionType(ret, [vp]).as_pointer())
        return builder.call(f, [builder.inttoptr(args[1], vp)])

    @intrinsic
    def _next_uint64(typingctx, fn, state):
        """``uint64_t next_uint64(void *state)`` of a bit generator at address ``fn``."""
        return types.uint64(types.intp, types.intp), lambda ctx, b, sig, args: _call_state_fn(b, args, ir.IntType(64))

    @intrinsic
    def _next_double(typingctx, fn, state):
        """``double next_double(void *state)`` of a bit generator at address ``fn`` (what
        ``Generator.random()`` returns)."""
        return types.float64(types.intp, types.intp), lambda ctx, b, sig, args: _call_state_fn(b, args, ir.DoubleType())

    @numba.njit(cache=True, nogil=True)
    def standard_normal(state, u64, f64):  # pragma: no cover - compiled
        """One ``Generator.standard_normal()`` draw: numpy's ziggurat (random_standard_normal in
        numpy/random/src/distributions/distributions.c) on the same bit generator, so the same
        double from the same stream (tests/velociroach/test_sim.py compares 10^5 draws)."""
        while True:
            r = _next_uint64(u64, state)
            idx = r & 0xFF
            r >>= 8
            sign = r & 0x1
            rabs = (r >> 1) & 0x000FFFFFFFFFFFFF
            x = rabs * wi_double[idx]
            if sign & 0x1:
                x = -x
            if rabs < ki_double[idx]:
                return x  # 99.3 % of the draws
            if idx == 0:  # the tail
                while True:
                    xx = -ziggurat_nor_inv_r * math.log1p(-_next_double(f64, state))
                    yy = -math.log1p(-_next_double(f64, state))
                    if yy + yy > xx * xx:
                        return -(ziggurat_nor_r + xx) if (rabs >> 8) & 0x1 else ziggurat_nor_r + xx
            elif (fi_double[idx - 1] - fi_double[idx]) * _next_double(f64, state) + fi_double[idx] < \
                    math.exp(-0.5 * x * x):
                return x

    @numba.njit(cache=True, nogil=True)
    def draws(state, u64, f64, out):  # pragma: no cover - compiled
        """``out[j] = (random(), standard_normal() x 6)`` for each row: the mocap sample's draws."""
        for j in range(out.shape[0]):
            out[j, 0] = _next_double(f64, state)
            for i in range(1, 7):
                out[j, i] = standard_normal(state, u64, f64)

    @numba.njit(cache=True, nogil=True)
    def run(step_fn, m_ptr, d_ptr, qpos, qvel, ctrl, vl_i, vr_i, n, substeps, st, c, rng_state, rng_u64, rng_f64,
            mq, ist, tile):  # pragma: no cover - compiled
        """Up to ``n`` ticks; stops before a tick on which the watchdog would trip, or after the
        tick whose mocap sample filled ``mq``. Returns the ticks done.

        ``st`` (read and written): the PID's integrals and last errors, duties, the last PID
        tick's battery voltage and currents, state of charge, battery voltage, motor currents,
        sim time, the next mocap sample's time; ``c``: setpoints, gains, limits, watchdog, motor
        and battery constants, then the mocap model's (period, terrain wrap period or 0, dropout,
        latency, noise, heading offset as cos/sin of its half angle, the mocap offset); ``ist``
        (read and written): the first free row of ``mq`` (the mocap queue), samples taken and
        dropped, the row after the newest lost or non-finite sample; ``tile``: the terrain wrap's offset (backend.py builds all of them, in that
        order). A mocap sample is ``VelociRoachSim._wrap`` then ``_mocap_sample``, the same
        operations on the same doubles with the same draws from the backend's mocap Generator
        (``rng_*``: backend.py's ``bit_generator_pointers``; :func:`standard_normal` is numpy's
        algorithm), written as one row of ``mq`` (arrival time, sample time, position,
        quaternion wxyz, ok, finite)."""
        int_l, int_r, pe_l, pe_r = st[0], st[1], st[2], st[3]
        dl, dr, vin, ci_l, ci_r = st[4], st[5], st[6], st[7], st[8]
        soc, vbat, i_l, i_r, t = st[9], st[10], st[11], st[12], st[13]
        mocap_t = st[14]
        sp_l, sp_r, kp, ki, ff_v, kd, lim, max_duty = c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]
        last_cmd, wd, r_m, ke, i_max, r_b, cap_as, idle = c[8], c[9], c[10], c[11], c[12], c[13], c[14], c[15]
        v_empty, v_span, tick_s, inv2pi = c[16], c[17], c[18], c[19]
        m_period, wrap, dropout, latency, s_pos, s_rot = c[20], c[21], c[22], c[23], c[24], c[25]
        turn, hc, hs, off_x, off_y, off_z = c[26], c[27], c[28], c[29], c[30], c[31]
        row, cap = ist[0], mq.shape[0]
        k = 0
        while k < n:
            if not (t - last_cmd <= wd):
                break
            wl = qvel[vl_i]
            wr = qvel[vr_i]
            vin, ci_l, ci_r = vbat, i_l, i_r
            vb = vbat if vbat > 1.0 else 1.0
            ff = ff_v / vb
            el = sp_l - wl * inv2pi
            er = sp_r - wr * inv2pi
            if ki > 0.0:
                il = int_l + el * tick_s
                ir_ = int_r + er * tick_s
                int_l = lim if il > lim else (-lim if il < -lim else il)
                int_r = lim if ir_ > lim else (-lim if ir_ < -lim else ir_)
            dl = ff * sp_l + kp * el + ki * int_l + kd * (el - pe_l)
            dr = ff * sp_r + kp * er + ki * int_r + kd * (er - pe_r)
            pe_l, pe_r = el, er
            dl = max_duty if dl > max_duty else (-max_duty if dl < -max_duty else dl)
            dr = max_duty if dr > max_duty else (-max_duty if dr < -max_duty else dr)
            i_tot = abs(i_l) + abs(i_r) + idle
            soc -= i_tot * tick_s / cap_as
            if soc < 0.0:
                soc = 0.0
            vbat = v_empty + v_span * soc - r_b * i_tot
            vl, vr = dl * vbat, dr * vbat
            i_l = (vl - ke * wl) / r_m
            i_r = (vr - ke * wr) / r_m
            i_l = i_max if i_l > i_max else (-i_max if i_l < -i_max else i_l)
            i_r = i_max if i_r > i_max else (-i_max if i_r < -i_max else i_r)
            ctrl[0] = vl
            ctrl[1] = vr
            for _ in range(substeps):
                _mj_step(step_fn, m_ptr, d_ptr)
            t += tick_s
            k += 1
            if t >= mocap_t - 1e-9:
                if wrap > 0.0:  # VelociRoachSim._wrap
                    for i in range(2):
                        if qpos[i] > 0.5 * wrap:
                            qpos[i] -= wrap
                            tile[i] += wrap
                        elif qpos[i] < -0.5 * wrap:
                            qpos[i] += wrap
                            tile[i] -= wrap
                # VelociRoachSim._mocap_sample
                q0, q1, q2, w, x, y, z = qpos[0], qpos[1], qpos[2], qpos[3], qpos[4], qpos[5], qpos[6]
                ist[1] += 1
                u = _next_double(rng_f64, rng_state)  # Generator.random()
                n0 = standard_normal(rng_state, rng_u64, rng_f64)
                n1 = standard_normal(rng_state, rng_u64, rng_f64)
                n2 = standard_normal(rng_state, rng_u64, rng_f64)
                n3 = standard_normal(rng_state, rng_u64, rng_f64)
                n4 = standard_normal(rng_state, rng_u64, rng_f64)
                n5 = standard_normal(rng_state, rng_u64, rng_f64)
                ok = u >= dropout
                if not ok:
                    ist[2] += 1
                p0 = q0 + (off_x + tile[0]) + s_pos * n0
                p1 = q1 + (off_y + tile[1]) + s_pos * n1
                p2 = q2 + (off_z + tile[2]) + s_pos * n2
                if s_rot > 0.0:
                    vx, vy, vz = s_rot * n3, s_rot * n4, s_rot * n5
                    ang = math.sqrt(vx * vx + vy * vy + vz * vz)
                    kk = math.sin(0.5 * ang) / ang if ang > 1e-12 else 0.5
                    aw, ax, ay, az = math.cos(0.5 * ang), kk * vx, kk * vy, kk * vz
                    w, x, y, z = (
                        aw * w - ax * x - ay * y - az * z,
                        aw * x + ax * w + ay * z - az * y,
                        aw * y - ax * z + ay * w + az * x,
                        aw * z + ax * y - ay * x + az * w,
                    )
                if turn != 0.0:
                    w, x, y, z = hc * w - hs * z, hc * x - hs * y, hc * y + hs * x, hc * z + hs * w
                r = mq[row]
                r[0], r[1], r[2], r[3], r[4] = t + latency, t, p0, p1, p2
                r[5], r[6], r[7], r[8] = w, x, y, z
                finite = (math.isfinite(p0) and math.isfinite(p1) and math.isfinite(p2) and math.isfinite(w)
                          and math.isfinite(x) and math.isfinite(y) and math.isfinite(z))
                r[9] = 1.0 if ok else 0.0
                r[10] = 1.0 if finite else 0.0
                row += 1
                if not (ok and finite):
                    ist[3] = row  # the queue holds a lost or unusable sample up to here
                mocap_t += m_period
                if row >= cap:
                    break
        st[0], st[1], st[2], st[3] = int_l, int_r, pe_l, pe_r
        st[4], st[5], st[6], st[7], st[8] = dl, dr, vin, ci_l, ci_r
        st[9], st[10], st[11], st[12], st[13] = soc, vbat, i_l, i_r, t
        st[14] = mocap_t
        ist[0] = row
        return k
