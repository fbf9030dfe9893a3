"""The ``axis`` model's two sequential loops compiled with numba (the ``speed`` extra), when installed.

* :func:`replay` is the open-loop replay of :func:`hilstack.calibration.axis._replay_numpy`: the
  same operations in the same order on the same doubles, one window at a time instead of one step
  of all windows at a time. The numpy version pays ~15 array operations per step of the horizon
  whatever the number of windows; an output-error refinement replays a few hundred windows for
  about 20 trust-region evaluations in every fit, so that overhead was most of a calibration's
  cost (docs/calibration.md, "Issue 28, round 6").
* :func:`backlash_play` is the play operator of :func:`hilstack.calibration.axis.backlash_play`.

Without numba both are None and the numpy / Python versions run; the results agree to rounding
(``tests/calibration/test_calib_speed.py``: sin and exp may differ in the last bit between numpy's
and LLVM's libraries, nothing else does).
"""

from __future__ import annotations

try:
    import numba
except ImportError:  # the speed extra is not installed
    numba = None

replay = None
backlash_play = None

#: Columns of the per-window coefficient matrix of a replay (see ``axis._with_coef``).
COEF_COLUMNS = ("a", "kb", "offset_acc", "gravity_acc", "c_per_s", "fc_acc", "fs_extra_acc", "fa_acc",
                "gl_acc", "gc_acc", "kemf")

if numba is not None:
    import math

    @numba.njit(cache=True, nogil=True)
    def _sign(x):
        if x > 0.0:
            return 1.0
        if x < 0.0:
            return -1.0
        if x == 0.0:
            return 0.0
        return x  # NaN stays NaN, as np.sign

    @numba.njit(cache=True, nogil=True)
    def replay(dt, horizon, idx0, x0, v0, xload0, has_play, play, vs, q0, cog_k, cog_phase, coef,
               u_in, kb_in, g, xs, vs_out):  # pragma: no cover - compiled
        for i in range(idx0.shape[0]):
            a, kb, off, grav = coef[i, 0], coef[i, 1], coef[i, 2], coef[i, 3]
            cps, fc, fs, fa = coef[i, 4], coef[i, 5], coef[i, 6], coef[i, 7]
            gl, gc, kemf = coef[i, 8], coef[i, 9], coef[i, 10]
            fric = fc != 0.0 or fs != 0.0 or fa != 0.0
            x, v, x_load = x0[i], v0[i], xload0[i]
            k = idx0[i]
            for h in range(horizon):
                gk = g[k]
                drive = a * u_in[k] + kb * kb_in[k] + off * gk + grav
                v_pred = v + dt * (drive - cps * gk * v)
                if kemf != 0.0:
                    v_pred = v_pred - dt * kemf * u_in[k] * v
                if gl != 0.0:
                    v_pred = v_pred - dt * gk * gl * math.sin(x - q0[i])
                if gc != 0.0:
                    v_pred = v_pred - dt * gk * gc * math.sin(cog_k[i] * x - cog_phase[i])
                if fric:
                    mag = fc + fa * _sign(v_pred)
                    if fs != 0.0:
                        r = v / vs[i]
                        mag = mag + fs * math.exp(-(r * r))
                    step = dt * gk * mag
                    if step > 0.0:
                        v_new = 0.0 if abs(v_pred) <= step else v_pred - step * _sign(v_pred)
                    else:
                        v_new = v_pred - step * _sign(v)
                else:
                    v_new = v_pred
                x = x + dt * 0.5 * (v + v_new)
                v = v_new
                k += 1
                if has_play[i]:
                    x_next = min(max(x_load, x - play[i]), x + play[i])
                    vs_out[i, h] = v if x_next != x_load else 0.0
                    x_load = x_next
                    xs[i, h] = x_load
                else:
                    xs[i, h] = x
                    vs_out[i, h] = v

    @numba.njit(cache=True, nogil=True)
    def backlash_play(u, halfwidth):  # pragma: no cover - compiled
        out = u.copy()
        prev = u[0]
        for k in range(u.shape[0]):
            lo, hi = u[k] - halfwidth, u[k] + halfwidth
            prev = lo if prev < lo else (hi if prev > hi else prev)
            out[k] = prev
        return out
