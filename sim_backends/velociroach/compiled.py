"""The VelociRoACH sim's 1 kHz loop compiled with numba (the ``speed`` extra), when installed.

What it runs is the inlined loop of ``VelociRoachSim._advance`` (the firmware's leg-velocity
PID, the battery and the motor currents, ``mj_step``) for as long as nothing but the PID runs
and no Python work is due (a mocap sample, a towed payload, the watchdog): the same
operations in the same order on the same doubles, so the floats are identical
(tests/velociroach/test_sim.py). ``mj_step`` is called through its C entry point in the
MuJoCo library the bindings loaded (``MjModel._address``/``MjData._address``), so a
physics step costs no Python call. Without numba :func:`kernel` is None and the backend
runs the same loop in Python.

Why: at 1 ms physics steps the Python loop (about 40 float operations and a binding call
per step) cost as much as the physics in ``hil bench sim`` (docs/platform.md, "Sim speed").
"""

from __future__ import annotations

import ctypes
import functools
import glob
import os
from typing import Any

try:
    import numba
    from llvmlite import ir
    from numba import types
    from numba.extending import intrinsic
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

    @numba.njit(cache=True, nogil=True)
    def run(step_fn, m_ptr, d_ptr, qvel, ctrl, vl_i, vr_i, n, substeps, t_stop, st, c):  # pragma: no cover - compiled
        """Up to ``n`` ticks; stops after the tick that reaches ``t_stop`` (a mocap sample is
        due) or before a tick on which the watchdog would trip. Returns the ticks done.
        ``st`` (read and written): the PID's integrals and last errors, duties, the last
        PID tick's battery voltage and currents, state of charge, battery voltage, motor
        currents, sim time; ``c``: setpoints, gains, limits, watchdog, motor and battery
        constants (backend.py builds both, in that order)."""
        int_l, int_r, pe_l, pe_r = st[0], st[1], st[2], st[3]
        dl, dr, vin, ci_l, ci_r = st[4], st[5], st[6], st[7], st[8]
        soc, vbat, i_l, i_r, t = st[9], st[10], st[11], st[12], st[13]
        sp_l, sp_r, kp, ki, ff_v, kd, lim, max_duty = c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]
        last_cmd, wd, r_m, ke, i_max, r_b, cap_as, idle = c[8], c[9], c[10], c[11], c[12], c[13], c[14], c[15]
        v_empty, v_span, tick_s, inv2pi = c[16], c[17], c[18], c[19]
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
            if t >= t_stop:
                break
        st[0], st[1], st[2], st[3] = int_l, int_r, pe_l, pe_r
        st[4], st[5], st[6], st[7], st[8] = dl, dr, vin, ci_l, ci_r
        st[9], st[10], st[11], st[12], st[13] = soc, vbat, i_l, i_r, t
        return k
