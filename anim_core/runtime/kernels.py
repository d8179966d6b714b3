"""The compiled kernels of the runtimes (:mod:`anim_core.runtime.kinds`): per kind of clip one function that poses
one character (``_<kind>_one``), made into the kind's crowd kernel by one factory (:func:`crowd_kernel`; it
releases the GIL, so that :meth:`~anim_core.runtime.kinds._Runtime.pose` runs it on several threads at once);
a foot-locked hybrid's runs its base kind's and then the legs' IK (``_foot_lock``, each leg by :func:`solve_leg`,
which the run-time IK job of :mod:`anim_core.runtime.ik` runs too).  Without numba this module
defines no kernels (the runtimes refuse to pose; :mod:`anim_core.runtime.crowd` falls back to numpy).

Conventions as :mod:`anim_core.runtime.kinds`: float32 poses, float64 times and parameters, quaternions
``(w, x, y, z)``.
"""

from __future__ import annotations

import inspect
from typing import Any

import numpy as np

from .crowd import numba

if numba is not None:
    _njit = numba.njit(cache=True, fastmath=False, inline="always")

    @_njit
    def _clip_time(t, duration, mode):
        """(clip time, completed loops) as :func:`anim_core.math.clip.playback_time`."""
        if mode == 0:
            cycles = np.floor(t / duration)
            ct = min(max(t - cycles * duration, 0.0), duration)
            return ct, cycles
        if mode == 1:
            ct = t % (2.0 * duration)
            if ct > duration:
                ct = 2.0 * duration - ct
            return ct, 0.0
        return min(max(t, 0.0), duration), 0.0

    @_njit
    def fk_joint(c, j, w, x, y, z, rx, ry, rz, parents, offsets, out_rot, out_pos):
        """Write joint ``j`` of character ``c`` from its local rotation (and, for the root, its translation)."""
        p = parents[j]
        ox, oy, oz = offsets[j, 0], offsets[j, 1], offsets[j, 2]
        if p < 0:
            out_rot[c, j, 0], out_rot[c, j, 1], out_rot[c, j, 2], out_rot[c, j, 3] = w, x, y, z
            out_pos[c, j, 0], out_pos[c, j, 1], out_pos[c, j, 2] = ox + rx, oy + ry, oz + rz
            return
        pw, px, py, pz = out_rot[c, p, 0], out_rot[c, p, 1], out_rot[c, p, 2], out_rot[c, p, 3]
        out_rot[c, j, 0] = pw * w - px * x - py * y - pz * z
        out_rot[c, j, 1] = pw * x + px * w + py * z - pz * y
        out_rot[c, j, 2] = pw * y - px * z + py * w + pz * x
        out_rot[c, j, 3] = pw * z + px * y - py * x + pz * w
        # offset rotated by the parent: v + 2w (u x v) + 2 u x (u x v)
        tx = np.float32(2.0) * (py * oz - pz * oy)
        ty = np.float32(2.0) * (pz * ox - px * oz)
        tz = np.float32(2.0) * (px * oy - py * ox)
        out_pos[c, j, 0] = out_pos[c, p, 0] + ox + pw * tx + (py * tz - pz * ty)
        out_pos[c, j, 1] = out_pos[c, p, 1] + oy + pw * ty + (pz * tx - px * tz)
        out_pos[c, j, 2] = out_pos[c, p, 2] + oz + pw * tz + (px * ty - py * tx)

    @_njit
    def _last_at_or_below(values, x, lo, hi):
        """The largest ``i`` in ``lo..hi`` with ``values[i] <= x`` (``lo`` if none): binary search, as
        ``searchsorted(values, x, "right") - 1`` clipped to ``lo..hi``."""
        while lo < hi:
            mid = (lo + hi + 1) // 2
            if values[mid] <= x:
                lo = mid
            else:
                hi = mid - 1
        return lo

    @_njit
    def _key_segment(ct, dt, key_times, n):
        """Key ``i`` before clip time ``ct`` and the fraction towards key ``i + 1``: on a grid of step ``dt``, or
        (``dt == 0``) searched in ``key_times``, as :meth:`KeyframeClip.sample` finds it."""
        if dt > 0.0:
            f = ct / dt
            i = min(max(int(np.floor(f)), 0), n - 2)
            return i, f - i
        i = _last_at_or_below(key_times, ct, 0, n - 2)
        return i, (ct - key_times[i]) / (key_times[i + 1] - key_times[i])

    @_njit
    def _table_one(c, keys, roots, velocity, params, key_times, times, parents, offsets, active, out_rot,
                   out_pos):
        dt, duration, mode = params[0], params[1], int(params[2])
        ct, cycles = _clip_time(times[c], duration, mode)
        i, f = _key_segment(ct, dt, key_times, keys.shape[0])
        a = np.float32(f)
        b = np.float32(1.0) - a
        travel = ct + cycles * duration
        rx = b * roots[i, 0] + a * roots[i + 1, 0] + velocity[0] * travel
        ry = b * roots[i, 1] + a * roots[i + 1, 1] + velocity[1] * travel
        rz = b * roots[i, 2] + a * roots[i + 1, 2] + velocity[2] * travel
        for j in range(keys.shape[1]):
            if active[j]:
                w = b * keys[i, j, 0] + a * keys[i + 1, j, 0]
                x = b * keys[i, j, 1] + a * keys[i + 1, j, 1]
                y = b * keys[i, j, 2] + a * keys[i + 1, j, 2]
                z = b * keys[i, j, 3] + a * keys[i + 1, j, 3]
                inv = np.float32(1.0) / np.sqrt(w * w + x * x + y * y + z * z)
                w, x, y, z = w * inv, x * inv, y * inv, z * inv
            else:
                w, x, y, z = keys[0, j, 0], keys[0, j, 1], keys[0, j, 2], keys[0, j, 3]
            fk_joint(c, j, w, x, y, z, rx, ry, rz, parents, offsets, out_rot, out_pos)

    @_njit
    def _root_spline(ct, root_times, root_coef):
        """The root spline of the whole period at clip time ``ct``, Horner in seconds from its segment's start."""
        r = 0
        while r < root_times.shape[0] - 2 and ct >= root_times[r + 1]:
            r += 1
        dx = np.float32(ct - root_times[r])
        rx = ((root_coef[r, 0, 0] * dx + root_coef[r, 1, 0]) * dx + root_coef[r, 2, 0]) * dx + root_coef[r, 3, 0]
        ry = ((root_coef[r, 0, 1] * dx + root_coef[r, 1, 1]) * dx + root_coef[r, 2, 1]) * dx + root_coef[r, 3, 1]
        rz = ((root_coef[r, 0, 2] * dx + root_coef[r, 1, 2]) * dx + root_coef[r, 2, 2]) * dx + root_coef[r, 3, 2]
        return rx, ry, rz

    @_njit
    def _spline_one(c, seg_times, ctrl, root_times, root_coef, src, mirror_map, velocity, params, times, parents,
                    offsets, active, out_rot, out_pos):
        duration, mode, half = params[0], int(params[1]), params[2]
        ct, cycles = _clip_time(times[c], duration, mode)
        rx, ry, rz = _root_spline(ct, root_times, root_coef)
        travel = ct + cycles * duration
        rx += velocity[0] * travel
        ry += velocity[1] * travel
        rz += velocity[2] * travel
        mirrored = half > 0.0 and ct >= half
        if mirrored:
            ct -= half
        s = 0
        while s < seg_times.shape[0] - 2 and ct >= seg_times[s + 1]:
            s += 1
        h = (ct - seg_times[s]) / (seg_times[s + 1] - seg_times[s])
        h = min(max(h, 0.0), 1.0)
        g = 1.0 - h
        b0, b1 = np.float32(g * g * g), np.float32(3.0 * g * g * h)
        b2, b3 = np.float32(3.0 * g * h * h), np.float32(h * h * h)
        k = 3 * s
        rows = mirror_map.shape[0]
        for j in range(ctrl.shape[1]):
            if active[j]:
                m = src[j] if mirrored else j
                w = b0 * ctrl[k, m, 0] + b1 * ctrl[k + 1, m, 0] + b2 * ctrl[k + 2, m, 0] + b3 * ctrl[k + 3, m, 0]
                x = b0 * ctrl[k, m, 1] + b1 * ctrl[k + 1, m, 1] + b2 * ctrl[k + 2, m, 1] + b3 * ctrl[k + 3, m, 1]
                y = b0 * ctrl[k, m, 2] + b1 * ctrl[k + 1, m, 2] + b2 * ctrl[k + 2, m, 2] + b3 * ctrl[k + 3, m, 2]
                z = b0 * ctrl[k, m, 3] + b1 * ctrl[k + 1, m, 3] + b2 * ctrl[k + 2, m, 3] + b3 * ctrl[k + 3, m, 3]
                inv = np.float32(1.0) / np.sqrt(w * w + x * x + y * y + z * z)
                w, x, y, z = w * inv, x * inv, y * inv, z * inv
                if mirrored:
                    mm = mirror_map[j if rows > 1 else 0]
                    w, x, y, z = (mm[0, 0] * w + mm[0, 1] * x + mm[0, 2] * y + mm[0, 3] * z,
                                  mm[1, 0] * w + mm[1, 1] * x + mm[1, 2] * y + mm[1, 3] * z,
                                  mm[2, 0] * w + mm[2, 1] * x + mm[2, 2] * y + mm[2, 3] * z,
                                  mm[3, 0] * w + mm[3, 1] * x + mm[3, 2] * y + mm[3, 3] * z)
            else:
                w, x, y, z = ctrl[0, j, 0], ctrl[0, j, 1], ctrl[0, j, 2], ctrl[0, j, 3]
            fk_joint(c, j, w, x, y, z, rx, ry, rz, parents, offsets, out_rot, out_pos)

    @_njit
    def crouch_path_parameter(ct, params):
        """Path parameter ``u`` at clip time ``ct``: ``(1 - spring(time_scale ct)) * normalization``, the closed
        form of :func:`anim_core.methods.hybrid.spring` from rest at 1 (the one place the crouch's timing lives)."""
        zeta, omega, ts, norm = params[0], params[1], params[2], params[3]
        x = ts * ct
        alpha = omega * np.sqrt(1.0 - zeta * zeta)
        spring = np.exp(-omega * zeta * x) * (np.cos(alpha * x) + omega * zeta / alpha * np.sin(alpha * x))
        return (1.0 - spring) * norm

    @_njit
    def _spring_one(c, key_params, keys, angles, inv_sin, key_root, params, times, parents, offsets,
                    active, out_rot, out_pos):
        ct, _ = _clip_time(times[c], params[4], int(params[5]))
        u = crouch_path_parameter(ct, params)
        s = 0
        while s < key_params.shape[0] - 2 and u >= key_params[s + 1]:
            s += 1
        local = (u - key_params[s]) / (key_params[s + 1] - key_params[s])  # not clamped: > 1 past the last key
        rx = key_root[s, 0] + (key_root[s + 1, 0] - key_root[s, 0]) * local
        ry = key_root[s, 1] + (key_root[s + 1, 1] - key_root[s, 1]) * local
        rz = key_root[s, 2] + (key_root[s + 1, 2] - key_root[s, 2]) * local
        lf = np.float32(local)
        for j in range(keys.shape[1]):
            if active[j]:
                om = angles[s, j]
                if inv_sin[s, j] != 0.0:
                    wa = np.sin((np.float32(1.0) - lf) * om) * inv_sin[s, j]
                    wb = np.sin(lf * om) * inv_sin[s, j]
                else:
                    wa, wb = np.float32(1.0) - lf, lf
                w = wa * keys[s, j, 0] + wb * keys[s + 1, j, 0]
                x = wa * keys[s, j, 1] + wb * keys[s + 1, j, 1]
                y = wa * keys[s, j, 2] + wb * keys[s + 1, j, 2]
                z = wa * keys[s, j, 3] + wb * keys[s + 1, j, 3]
            else:
                w, x, y, z = keys[0, j, 0], keys[0, j, 1], keys[0, j, 2], keys[0, j, 3]
            fk_joint(c, j, w, x, y, z, rx, ry, rz, parents, offsets, out_rot, out_pos)

    @_njit
    def _dequantize(codes, low, step, k, j):
        """Key ``k`` of joint ``j`` dequantized and normalized (float32)."""
        w = low[j, 0] + np.float32(codes[k, j, 0]) * step[j, 0]
        x = low[j, 1] + np.float32(codes[k, j, 1]) * step[j, 1]
        y = low[j, 2] + np.float32(codes[k, j, 2]) * step[j, 2]
        z = low[j, 3] + np.float32(codes[k, j, 3]) * step[j, 3]
        inv = np.float32(1.0) / np.sqrt(w * w + x * x + y * y + z * z)
        return w * inv, x * inv, y * inv, z * inv

    @_njit
    def _quantized_one(c, codes, low, step, roots, velocity, params, key_times, times, parents, offsets, active,
                       out_rot, out_pos):
        dt, duration, mode = params[0], params[1], int(params[2])
        ct, cycles = _clip_time(times[c], duration, mode)
        i, f = _key_segment(ct, dt, key_times, codes.shape[0])
        a = np.float32(f)
        b = np.float32(1.0) - a
        travel = ct + cycles * duration
        rx = b * roots[i, 0] + a * roots[i + 1, 0] + velocity[0] * travel
        ry = b * roots[i, 1] + a * roots[i + 1, 1] + velocity[1] * travel
        rz = b * roots[i, 2] + a * roots[i + 1, 2] + velocity[2] * travel
        for j in range(codes.shape[1]):
            if active[j]:
                w0, x0, y0, z0 = _dequantize(codes, low, step, i, j)
                w1, x1, y1, z1 = _dequantize(codes, low, step, i + 1, j)
                w, x, y, z = b * w0 + a * w1, b * x0 + a * x1, b * y0 + a * y1, b * z0 + a * z1
                inv = np.float32(1.0) / np.sqrt(w * w + x * x + y * y + z * z)
                w, x, y, z = w * inv, x * inv, y * inv, z * inv
            else:
                w, x, y, z = _dequantize(codes, low, step, 0, j)
            fk_joint(c, j, w, x, y, z, rx, ry, rz, parents, offsets, out_rot, out_pos)

    @_njit
    def _c2_one(c, knots, control, steps, root_times, root_coef, velocity, params, times, parents, offsets,
                active, out_rot, out_pos):
        duration, mode, period, t0 = params[0], int(params[1]), params[2], params[3]
        ct, cycles = _clip_time(times[c], duration, mode)
        rx, ry, rz = _root_spline(ct, root_times, root_coef)
        travel = ct + cycles * duration
        rx += velocity[0] * travel
        ry += velocity[1] * travel
        rz += velocity[2] * travel
        k = control.shape[0]
        tt = t0 + (ct - t0) - np.floor((ct - t0) / period) * period
        span = _last_at_or_below(knots, tt, 3, k + 2)
        # The four cubic B-spline basis functions on this span (The NURBS Book A2.2, unrolled for degree 3).
        l1, l2, l3 = tt - knots[span], tt - knots[span - 1], tt - knots[span - 2]
        r1, r2, r3 = knots[span + 1] - tt, knots[span + 2] - tt, knots[span + 3] - tt
        n0 = 1.0
        tmp = n0 / (r1 + l1)
        n0, n1 = r1 * tmp, l1 * tmp
        tmp0 = n0 / (r1 + l2)
        tmp1 = n1 / (r2 + l1)
        n0, n1, n2 = r1 * tmp0, l2 * tmp0 + r2 * tmp1, l1 * tmp1
        tmp0 = n0 / (r1 + l3)
        tmp1 = n1 / (r2 + l2)
        tmp2 = n2 / (r3 + l1)
        n1, n2, n3 = l3 * tmp0 + r2 * tmp1, l2 * tmp1 + r3 * tmp2, l1 * tmp2
        b1, b2, b3 = np.float32(n1 + n2 + n3), np.float32(n2 + n3), np.float32(n3)  # cumulative basis
        m = span - 3
        i0, i1, i2, i3 = (m - 1 + k) % k, m, (m + 1) % k, (m + 2) % k
        for j in range(control.shape[1]):
            if active[j]:
                w, x, y, z = control[i0, j, 0], control[i0, j, 1], control[i0, j, 2], control[i0, j, 3]
                w, x, y, z = _times_exp(w, x, y, z, b1, steps, i1, j)
                w, x, y, z = _times_exp(w, x, y, z, b2, steps, i2, j)
                w, x, y, z = _times_exp(w, x, y, z, b3, steps, i3, j)
            else:
                w, x, y, z = control[0, j, 0], control[0, j, 1], control[0, j, 2], control[0, j, 3]
            fk_joint(c, j, w, x, y, z, rx, ry, rz, parents, offsets, out_rot, out_pos)

    @_njit
    def _times_exp(w, x, y, z, weight, steps, i, j):
        """``(w, x, y, z) exp(weight w_i)`` for joint ``j``, ``w_i`` stored as half angle and unit axis."""
        angle = weight * steps[i, j, 0]
        cs, sn = np.cos(angle), np.sin(angle)
        return _qmul(w, x, y, z, cs, sn * steps[i, j, 1], sn * steps[i, j, 2], sn * steps[i, j, 3])

    @_njit
    def _qmul(aw, ax, ay, az, bw, bx, by, bz):
        return (aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)

    @_njit
    def _qrot(w, x, y, z, vx, vy, vz):
        """``v`` rotated by the unit quaternion ``(w, x, y, z)``: v + 2w (u x v) + 2 u x (u x v)."""
        tx, ty, tz = 2.0 * (y * vz - z * vy), 2.0 * (z * vx - x * vz), 2.0 * (x * vy - y * vx)
        return vx + w * tx + (y * tz - z * ty), vy + w * ty + (z * tx - x * tz), vz + w * tz + (x * ty - y * tx)

    @_njit
    def _perpendicular(vx, vy, vz):
        """A unit vector perpendicular to ``v`` (as :func:`anim_core.methods.ik._perpendicular`)."""
        hx, hy = (1.0, 0.0) if abs(vx) < 0.9 else (0.0, 1.0)
        cx, cy, cz = -vz * hy, vz * hx, vx * hy - vy * hx
        n = np.sqrt(cx * cx + cy * cy + cz * cz)
        return cx / n, cy / n, cz / n

    @_njit
    def _axis_angle(ax, ay, az, angle):
        s = np.sin(0.5 * angle) / np.sqrt(ax * ax + ay * ay + az * az)
        return np.cos(0.5 * angle), ax * s, ay * s, az * s

    @_njit
    def _between(ax, ay, az, bx, by, bz):
        """The smallest rotation turning ``a`` into ``b`` (as :func:`anim_core.math.quat.quat_between`)."""
        aa = ax * ax + ay * ay + az * az
        w = np.sqrt(aa) * np.sqrt(bx * bx + by * by + bz * bz) + ax * bx + ay * by + az * bz
        x, y, z = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        n = np.sqrt(w * w + x * x + y * y + z * z)
        if n <= 1e-12 * max(aa, 1e-300):  # opposite: a half turn about an axis perpendicular to a
            hx, hy = (1.0, 0.0) if abs(ax) < 0.9 else (0.0, 1.0)
            w, x, y, z = 0.0, -az * hy, az * hx, ax * hy - ay * hx
            n = np.sqrt(x * x + y * y + z * z)
        return w / n, x / n, y / n, z / n

    @_njit
    def _hermite(values, slopes, i, leg, q, h00, h10, h01, h11):
        """Component ``q`` of leg ``leg``'s track on the piece from point ``i`` (basis weights given)."""
        return (h00 * values[i, leg, q] + h10 * slopes[i, leg, q] + h01 * values[i + 1, leg, q]
                + h11 * slopes[i + 1, leg, q])

    @_njit
    def _foot_lock(c, chains, hinges, below, turns, values, slopes, ik, times, parents, offsets, out_rot, out_pos):
        """Both legs of character ``c`` (posed by the base kernel) solved towards their tracks' targets by
        :func:`solve_leg`."""
        fps, loop, duration, mode, soft, straight = ik[0], ik[1], ik[2], int(ik[3]), ik[7], ik[8]
        ct, cycles = _clip_time(times[c], duration, mode)
        travel = ct + cycles * duration
        n = values.shape[0]
        f = ct * fps
        if loop > 0.0:  # periodic tracks: the last point is the first one again
            f -= np.floor(f / (n - 1)) * (n - 1)
        i = min(max(int(np.floor(f)), 0), n - 2)
        u = f - i  # past 1 at a ping-pong clip's end: the last piece extrapolated, as the spline does
        h = 1.0 / fps
        h00, h10 = (2.0 * u - 3.0) * u * u + 1.0, ((u - 2.0) * u + 1.0) * u * h
        h01, h11 = (3.0 - 2.0 * u) * u * u, (u - 1.0) * u * u * h
        for leg in range(chains.shape[0]):
            weight = min(max(_hermite(values, slopes, i, leg, 3, h00, h10, h01, h11), 0.0), 1.0)
            if weight <= 0.0:
                continue
            solve_leg(c, leg, chains, hinges, below, turns, weight,
                      _hermite(values, slopes, i, leg, 0, h00, h10, h01, h11) + ik[4] * travel,
                      _hermite(values, slopes, i, leg, 1, h00, h10, h01, h11) + ik[5] * travel,
                      _hermite(values, slopes, i, leg, 2, h00, h10, h01, h11) + ik[6] * travel,
                      soft, straight, parents, offsets, out_rot, out_pos)

    @_njit
    def solve_leg(c, leg, chains, hinges, below, turns, weight, tx, ty, tz, soft, straight, parents, offsets,
                  out_rot, out_pos):
        """Leg ``leg`` (``chains[leg]`` = hip, knee, ankle) of character ``c``, posed in model space in ``out_rot``
        / ``out_pos``, solved towards the model-space target ``t`` blended from the animated ankle by ``weight``
        (0..1): the steps of :func:`anim_core.methods.ik.two_bone_ik` with the knee's hinge (``hinges[leg]``, in
        the knee's frame), no pole, the soft reach ``soft`` and the ankle's world orientation kept, in float64;
        the hip's and knee's global rotations turn, every joint under the hip is re-placed (``below``, ``turns``).
        Shared by the foot-locked hybrid's kernel and the run-time IK job (:mod:`anim_core.runtime.ik`)."""
        s, m, e = chains[leg, 0], chains[leg, 1], chains[leg, 2]
        sx, sy, sz = np.float64(out_pos[c, s, 0]), np.float64(out_pos[c, s, 1]), np.float64(out_pos[c, s, 2])
        mx, my, mz = np.float64(out_pos[c, m, 0]), np.float64(out_pos[c, m, 1]), np.float64(out_pos[c, m, 2])
        ex, ey, ez = np.float64(out_pos[c, e, 0]), np.float64(out_pos[c, e, 1]), np.float64(out_pos[c, e, 2])
        tx = ex + weight * (tx - ex)
        ty = ey + weight * (ty - ey)
        tz = ez + weight * (tz - ez)
        a, b = _bone_length(offsets, m), _bone_length(offsets, e)
        dx, dy, dz, dist = _leg_reach(tx - sx, ty - sy, tz - sz, ex - sx, ey - sy, ez - sz, mx - sx, my - sy,
                                      mz - sz, a, b, soft)
        thx, thy, thz = mx - sx, my - sy, mz - sz
        shx, shy, shz = ex - mx, ey - my, ez - mz
        ux, uy, uz = thx / a, thy / a, thz / a
        hx, hy, hz = _qrot(np.float64(out_rot[c, m, 0]), np.float64(out_rot[c, m, 1]),
                           np.float64(out_rot[c, m, 2]), np.float64(out_rot[c, m, 3]),
                           np.float64(hinges[leg, 0]), np.float64(hinges[leg, 1]), np.float64(hinges[leg, 2]))
        vx, vy, vz = _knee_side(thx, thy, thz, shx, shy, shz, ux, uy, uz, hx, hy, hz, a, b, straight)
        nsx, nsy, nsz = _solved_shin(ux, uy, uz, vx, vy, vz, a, b, dist)
        mw, mqx, mqy, mqz = _between(shx, shy, shz, nsx, nsy, nsz)
        hip = _hip_turn(mx + nsx - sx, my + nsy - sy, mz + nsz - sz, dx, dy, dz, vx, vy, vz, a)
        knee = _qmul(hip[0], hip[1], hip[2], hip[3], mw, mqx, mqy, mqz)
        _turn_leg(c, leg, s, hip, knee, below, turns, parents, offsets, out_rot, out_pos)

    @_njit
    def _bone_length(offsets, j):
        """The length of joint ``j``'s offset in float64 (in float32, ``a * a + b * b - d * d`` near full reach
        rounds by more than the solve's 1e-9 margin, and the bend of a leg at full reach came out 0.006 degrees
        off the offline solve's)."""
        x, y, z = np.float64(offsets[j, 0]), np.float64(offsets[j, 1]), np.float64(offsets[j, 2])
        return np.sqrt(x * x + y * y + z * z)

    # solve_leg's steps, as two_bone_ik's, on scalars: a numba kernel takes no small arrays without allocating, and
    # these are inlined (inline="always"), so the compiled kernel is the one-function kernel it was.
    @_njit
    def _leg_reach(dx, dy, dz, fx, fy, fz, thx, thy, thz, a, b, soft):
        """Step 1: unit direction and clamped (and softened) distance from hip to target ``d``; ``f`` (hip to the
        animated ankle), then a perpendicular of the thigh ``th``, stand in for a target on the hip."""
        dist = np.sqrt(dx * dx + dy * dy + dz * dz)
        if dist > 1e-12:
            dx, dy, dz = dx / dist, dy / dist, dz / dist
        else:
            fn = np.sqrt(fx * fx + fy * fy + fz * fz)
            if fn > 1e-12:
                dx, dy, dz = fx / fn, fy / fn, fz / fn
            else:
                dx, dy, dz = _perpendicular(thx, thy, thz)
        if soft > 0.0 and dist > a + b - soft:
            dist = a + b - soft - soft * np.expm1(-(dist - (a + b - soft)) / soft)
        dist = min(max(dist, abs(a - b) + 1e-9 * (a + b)), (a + b) * (1.0 - 1e-9))
        return dx, dy, dz, dist

    @_njit
    def _knee_side(thx, thy, thz, shx, shy, shz, ux, uy, uz, hx, hy, hz, a, b, straight):
        """Step 2's plane normal ``side``: the animated one (thigh ``th`` x shin ``sh``) turned to the side of the
        hinge ``h`` (world), easing into the hinge's own plane as the animated leg straightens (``u``: the thigh's
        direction)."""
        cx, cy, cz = thy * shz - thz * shy, thz * shx - thx * shz, thx * shy - thy * shx
        cn = np.sqrt(cx * cx + cy * cy + cz * cz)
        hu = hx * ux + hy * uy + hz * uz
        qx, qy, qz = hx - hu * ux, hy - hu * uy, hz - hu * uz
        qn = np.sqrt(qx * qx + qy * qy + qz * qz)
        if qn > 1e-12:
            qx, qy, qz = qx / qn, qy / qn, qz / qn
        else:
            qx, qy, qz = _perpendicular(thx, thy, thz)
        flip = -1.0 if cx * hx + cy * hy + cz * hz < 0.0 else 1.0
        ease = min(max(cn / (straight * a * b), 0.0), 1.0)
        ease = ease * ease * (3.0 - 2.0 * ease)
        nx, ny, nz = (cx / cn, cy / cn, cz / cn) if cn > 1e-12 else (qx, qy, qz)
        vx = ease * flip * nx + (1.0 - ease) * qx
        vy = ease * flip * ny + (1.0 - ease) * qy
        vz = ease * flip * nz + (1.0 - ease) * qz
        vn = np.sqrt(vx * vx + vy * vy + vz * vz)
        if vn > 1e-12:
            vx, vy, vz = vx / vn, vy / vn, vz / vn
        else:
            vx, vy, vz = qx, qy, qz
        return vx, vy, vz

    @_njit
    def _solved_shin(ux, uy, uz, vx, vy, vz, a, b, dist):
        """Step 2: the new shin, at the angle from the thigh (direction ``u``) in the plane of normal ``v`` at
        which the law of cosines gives ``dist``."""
        cos_inner = min(max((a * a + b * b - dist * dist) / (2.0 * a * b), -1.0), 1.0)
        bend = np.pi - np.arccos(cos_inner)  # 0 = straight
        cb, sb = b * np.cos(bend), b * np.sin(bend)
        wx, wy, wz = vy * uz - vz * uy, vz * ux - vx * uz, vx * uy - vy * ux  # side x thigh direction
        return cb * ux + sb * wx, cb * uy + sb * wy, cb * uz + sb * wz

    @_njit
    def _hip_turn(lx, ly, lz, dx, dy, dz, vx, vy, vz, a):
        """Step 3: the hip's turn that swings the ankle (``l``: hip to the bent leg's ankle) onto the target direction
        ``d``, then twists about it so the plane (``v``, carried by the swing) is as close as it gets to the
        animated one; ``a``: the thigh's length."""
        sw, swx, swy, swz = _between(lx, ly, lz, dx, dy, dz)
        px, py, pz = _qrot(sw, swx, swy, swz, vx, vy, vz)
        vd = vx * dx + vy * dy + vz * dz
        kx, ky, kz = vx - vd * dx, vy - vd * dy, vz - vd * dz  # wanted
        angle = 0.0
        if np.sqrt(kx * kx + ky * ky + kz * kz) > 1e-9 * a:
            angle = np.arctan2(dx * (py * kz - pz * ky) + dy * (pz * kx - px * kz) + dz * (px * ky - py * kx),
                               px * kx + py * ky + pz * kz)
        tw, twx, twy, twz = _axis_angle(dx, dy, dz, angle)
        return _qmul(tw, twx, twy, twz, sw, swx, swy, swz)

    @_njit
    def _turn_leg(c, leg, s, hip, knee, below, turns, parents, offsets, out_rot, out_pos):
        """The hip joint ``s`` turned by ``hip``, and every joint under it (``below``) turned as ``turns`` says
        (0: the hip's turn, 1: the knee's, 2: none) and re-placed from its parent."""
        g = _qmul(hip[0], hip[1], hip[2], hip[3], out_rot[c, s, 0], out_rot[c, s, 1], out_rot[c, s, 2],
                  out_rot[c, s, 3])
        out_rot[c, s, 0], out_rot[c, s, 1], out_rot[c, s, 2], out_rot[c, s, 3] = g
        for k in range(below.shape[1]):
            j = below[leg, k]
            if j < 0:
                break
            turn = turns[leg, k]
            if turn < 2:
                r = hip if turn == 0 else knee
                g = _qmul(r[0], r[1], r[2], r[3], out_rot[c, j, 0], out_rot[c, j, 1], out_rot[c, j, 2],
                          out_rot[c, j, 3])
                out_rot[c, j, 0], out_rot[c, j, 1], out_rot[c, j, 2], out_rot[c, j, 3] = g
            p = parents[j]
            ox, oy, oz = _qrot(np.float64(out_rot[c, p, 0]), np.float64(out_rot[c, p, 1]),
                               np.float64(out_rot[c, p, 2]), np.float64(out_rot[c, p, 3]),
                               np.float64(offsets[j, 0]), np.float64(offsets[j, 1]), np.float64(offsets[j, 2]))
            out_pos[c, j, 0] = out_pos[c, p, 0] + ox
            out_pos[c, j, 1] = out_pos[c, p, 1] + oy
            out_pos[c, j, 2] = out_pos[c, p, 2] + oz

    @numba.njit(cache=True, fastmath=False)
    def local_to_model(local, root, parents, offsets, out_rot, out_pos):
        """The local-to-model job's kernel (:func:`anim_core.runtime.blending.local_to_model`): every joint of
        every character by :func:`fk_joint`.  Here, as :func:`ik_job`, for numba's cache."""
        for c in range(local.shape[0]):
            for j in range(local.shape[1]):
                fk_joint(c, j, local[c, j, 0], local[c, j, 1], local[c, j, 2], local[c, j, 3],
                         root[c, 0], root[c, 1], root[c, 2], parents, offsets, out_rot, out_pos)

    @numba.njit(cache=True, fastmath=False)
    def ik_job(chains, hinges, below, turns, params, targets, weights, parents, offsets, out_rot, out_pos):
        """The run-time IK job's kernel (:class:`anim_core.runtime.ik.TwoBoneIKJob`): every leg of weight > 0 of
        every character solved by :func:`solve_leg` towards ``targets (N, F, 3)``; ``params`` = (soft reach, the
        IK's straight-knee threshold).  Here, beside :func:`solve_leg`, because numba's cache of a kernel is
        refreshed when its own file changes, not when a function it inlines from another file does."""
        soft, straight = params[0], params[1]
        for c in range(out_rot.shape[0]):
            for leg in range(chains.shape[0]):
                w = min(max(np.float64(weights[c, leg]), 0.0), 1.0)
                if w <= 0.0:
                    continue
                solve_leg(c, leg, chains, hinges, below, turns, w, np.float64(targets[c, leg, 0]),
                          np.float64(targets[c, leg, 1]), np.float64(targets[c, leg, 2]), soft, straight, parents,
                          offsets, out_rot, out_pos)

# The arguments every per-character function takes besides the runtime's arrays (its first is the character).
_SHARED = ("times", "parents", "offsets", "active", "out_rot", "out_pos")
_KERNEL = """
def {name}({arrays}, times, parents, offsets, active, first, stride, stop, out_rot, out_pos):
    for c in range(first, min(stop, times.shape[0]), stride):
        {calls}
"""


def crowd_kernel(*steps: Any) -> Any:
    """The kernel of one kind of runtime, which runs ``steps`` (per-character functions ``step(c, <its arrays>,
    <some of _SHARED>)``, e.g. a base kind's, then the foot locking) for characters ``first, first + stride, ...``.

    It takes the steps' arrays in order (the order of the runtime's :meth:`arrays`), then ``times, parents,
    offsets, active, first, stride, out_rot, out_pos``.  Its source is written from the steps' signatures, so that
    every array is an argument of its own (numba compiles a kernel per combination of argument types).  It is
    compiled as part of this file, so numba's on-disk cache holds it; without the GIL, so that threads can run it
    on disjoint characters at once (one kernel, not a serial and a ``prange`` one: a parallel compile cost several
    times the serial one, 10 s for a foot-locked kind; docs/reference/benchmark.md, *Threads*).  Without reference
    counting (it allocates nothing) and with numpy's error model (its inputs are validated, so no zero check before
    each division): together 15-20 % faster than numba's defaults."""
    arrays: list[str] = []
    calls = []
    for step in steps:
        params = list(inspect.signature(step.py_func).parameters)[1:]
        own = [p for p in params if p not in _SHARED]
        if clash := set(own) & set(arrays):
            raise ValueError(f"{step.__name__} names arrays of an earlier step: {sorted(clash)}")
        arrays += own
        calls.append(f"{step.__name__}(c, {', '.join(params)})")
    name = "_".join(step.__name__.strip("_") for step in steps)
    namespace = dict(globals())
    source = _KERNEL.format(name=name, arrays=", ".join(arrays), calls="\n        ".join(calls))
    exec(compile(source, __file__, "exec"), namespace)
    return numba.njit(cache=True, nogil=True, error_model="numpy", _nrt=False)(namespace[name])


if numba is not None:
    TABLE = crowd_kernel(_table_one)
    QUANTIZED = crowd_kernel(_quantized_one)
    SPLINE = crowd_kernel(_spline_one)
    SPRING = crowd_kernel(_spring_one)
    C2 = crowd_kernel(_c2_one)
    SPLINE_IK = crowd_kernel(_spline_one, _foot_lock)
    SPRING_IK = crowd_kernel(_spring_one, _foot_lock)
