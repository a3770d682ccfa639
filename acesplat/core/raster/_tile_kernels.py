"""Numba kernels over 16x16 pixel tiles: binning, front-to-back compositing and its backward replay.

Within a tile the loop runs over the tile's depth-sorted Gaussians and, for each, only over the
pixels inside its cut-off ellipse (row spans solved exactly), so the cost follows the Gaussians'
footprints rather than tile area. Each tile owns its pixels and its slots of the tile lists, so the
parallel loop over tiles has no races and the per-Gaussian gradient sums are deterministic.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ._layout import (
    BLUE, CA, CB, CC, DEPTH, EXT_X, EXT_Y, G_BLUE, G_CA, G_CB, G_CC, G_DEPTH, G_GREEN, G_MX, G_MY, G_OPAC,
    G_RED, GREEN, MAHA2, MX, MY, OPAC, POWER_MIN, RED,
)

TILE = 16
"""Tile edge in pixels."""

ALPHA_MAX = 0.99
"""Per-Gaussian alpha is clamped here so transmittance can be recovered by division in backward."""

T_MIN = 1e-4
"""Front-to-back compositing stops before transmittance would fall below this."""

_SPAN_SLACK = 1e-3
"""Pixels this close outside the solved ellipse span still get the exact exponent test."""


@njit(cache=True)
def bin_tiles(rec, bbox, order, n, tiles_x, tiles_y):
    """Bin the V visible Gaussians into per-tile lists.

    rec (V, REC_WIDTH) and bbox (V, 4) are already in depth order; order (V,) gives each one's
    index among all n Gaussians.

    Returns
    - tile_offsets (n_tiles + 1,) and tile_rec (M, REC_WIDTH): each tile's records copied
      contiguously in depth order (a stable counting sort), so compositing streams through memory
      instead of chasing depth-sorted indices across the record array (measured: that random
      access cost more than the compositing arithmetic);
    - g_offsets (N + 1,) over Gaussian index and entry_slot (M,): tile entry k's gradient goes to
      slot entry_slot[k], and Gaussian i's slots are g_offsets[i]:g_offsets[i + 1], contiguous, so
      the per-Gaussian reduction reads sequentially (the scattered side is the cheaper writes).
    """
    n_tiles = tiles_x * tiles_y
    tile_offsets = np.zeros(n_tiles + 1, np.int64)
    g_offsets = np.zeros(n + 1, np.int64)
    for s in range(order.shape[0]):
        i = order[s]
        tx0 = bbox[s, 0] // TILE
        tx1 = bbox[s, 1] // TILE
        ty0 = bbox[s, 2] // TILE
        ty1 = bbox[s, 3] // TILE
        for ty in range(ty0, ty1 + 1):
            for tx in range(tx0, tx1 + 1):
                tile_offsets[ty * tiles_x + tx + 1] += 1
        g_offsets[i + 1] = (tx1 - tx0 + 1) * (ty1 - ty0 + 1)
    for t in range(n_tiles):
        tile_offsets[t + 1] += tile_offsets[t]
    for i in range(n):
        g_offsets[i + 1] += g_offsets[i]
    m = tile_offsets[n_tiles]
    tile_rec = np.empty((m, rec.shape[1]), rec.dtype)
    entry_slot = np.empty(m, np.int64)
    cursor = np.empty(n_tiles, np.int64)
    for t in range(n_tiles):
        cursor[t] = tile_offsets[t]
    for s in range(order.shape[0]):
        i = order[s]
        tx0 = bbox[s, 0] // TILE
        tx1 = bbox[s, 1] // TILE
        ty0 = bbox[s, 2] // TILE
        ty1 = bbox[s, 3] // TILE
        j = g_offsets[i]
        for ty in range(ty0, ty1 + 1):
            for tx in range(tx0, tx1 + 1):
                t = ty * tiles_x + tx
                pos = cursor[t]
                cursor[t] = pos + 1
                for c in range(rec.shape[1]):
                    tile_rec[pos, c] = rec[s, c]
                entry_slot[pos] = j
                j += 1
    return tile_offsets, tile_rec, g_offsets, entry_slot


@njit(cache=True)
def _row_range(my, ey, ty0, ty1):
    """Rows of the tile [ty0, ty1] the Gaussian's ellipse can reach."""
    ya = int(max(ty0 * 1.0, math.ceil(my - ey)))
    yb = int(min(ty1 * 1.0, math.floor(my + ey)))
    return ya, yb


@njit(cache=True)
def _col_span(mx, dy, ca, cb, cc, maha2, tx0, tx1):
    """Columns of row offset dy = my - y inside ca dx^2 + 2 cb dx dy + cc dy^2 <= maha2 (dx = mx - x)."""
    q = cb * dy
    disc = q * q - ca * (cc * dy * dy - maha2)
    if disc < 0.0:
        return 1, 0
    root = math.sqrt(disc)
    xa = int(max(tx0 * 1.0, math.ceil(mx + (q - root) / ca - _SPAN_SLACK)))
    xb = int(min(tx1 * 1.0, math.floor(mx + (q + root) / ca + _SPAN_SLACK)))
    return xa, xb


@njit(cache=True)
def _composite_forward_tile(
    tile,
    tile_rec, tile_offsets, tile_order, tiles_x, width, height, background,
    out_color, out_trans, out_depth, out_last, done,
):
    ty = tile // tiles_x
    tx = tile - ty * tiles_x
    px0 = tx * TILE
    py0 = ty * TILE
    px1 = min(px0 + TILE, width) - 1
    py1 = min(py0 + TILE, height) - 1
    for y in range(py0, py1 + 1):
        for x in range(px0, px1 + 1):
            out_trans[y, x] = 1.0
            out_color[y, x, 0] = 0.0
            out_color[y, x, 1] = 0.0
            out_color[y, x, 2] = 0.0
            out_depth[y, x] = 0.0
            out_last[y, x] = 0
            done[y, x] = False
    active = (px1 - px0 + 1) * (py1 - py0 + 1)
    start = tile_offsets[tile]
    end = tile_offsets[tile + 1]
    for k in range(start, end):
        if active == 0:
            break
        mx = tile_rec[k, MX] * 1.0
        my = tile_rec[k, MY] * 1.0
        ca = tile_rec[k, CA] * 1.0
        cb = tile_rec[k, CB] * 1.0
        cc = tile_rec[k, CC] * 1.0
        op = tile_rec[k, OPAC] * 1.0
        cr = tile_rec[k, RED] * 1.0
        cg = tile_rec[k, GREEN] * 1.0
        cbl = tile_rec[k, BLUE] * 1.0
        z = tile_rec[k, DEPTH] * 1.0
        pmin = tile_rec[k, POWER_MIN] * 1.0
        maha2 = tile_rec[k, MAHA2] * 1.0
        ya, yb = _row_range(my, tile_rec[k, EXT_Y] * 1.0, py0, py1)
        n_in = k - start + 1
        for y in range(ya, yb + 1):
            dy = my - y
            xa, xb = _col_span(mx, dy, ca, cb, cc, maha2, px0, px1)
            for x in range(xa, xb + 1):
                if done[y, x]:
                    continue
                dx = mx - x
                power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                if not (power >= pmin):
                    continue
                alpha = min(ALPHA_MAX, op * math.exp(power))
                t = out_trans[y, x]
                t_next = t * (1.0 - alpha)
                if t_next < T_MIN:
                    done[y, x] = True
                    active -= 1
                    continue
                w = alpha * t
                out_color[y, x, 0] += w * cr
                out_color[y, x, 1] += w * cg
                out_color[y, x, 2] += w * cbl
                out_depth[y, x] += w * z
                out_trans[y, x] = t_next
                out_last[y, x] = n_in
    for y in range(py0, py1 + 1):
        for x in range(px0, px1 + 1):
            t = out_trans[y, x]
            out_color[y, x, 0] += t * background[0]
            out_color[y, x, 1] += t * background[1]
            out_color[y, x, 2] += t * background[2]


@njit(nogil=True, cache=True)
def composite_forward(
    lo, hi, tile_rec, tile_offsets, tile_order, tiles_x, width, height, background,
    out_color, out_trans, out_depth, out_last, done,
):
    """Front-to-back alpha compositing per tile.

    Writes out_color (H, W, 3) including background, out_trans (H, W) final transmittance,
    out_depth (H, W) the alpha-weighted depth sum, and out_last (H, W) the number of list entries
    up to and including the last contributor (what the backward replay starts from).

    Handles tiles tile_order[lo:hi] and releases the GIL: chunks run on a thread pool.
    """
    for oi in range(lo, hi):
        _composite_forward_tile(
            tile_order[oi],
            tile_rec, tile_offsets, tile_order, tiles_x, width, height, background,
            out_color, out_trans, out_depth, out_last, done,
        )


@njit(cache=True)
def _composite_backward_tile(
    tile,
    tile_rec, tile_offsets, tile_order, tiles_x, width, height, background,
    final_trans, last, v_color, v_alpha, v_depth, entry_slot, scratch, slot_grads,
):
    ty = tile // tiles_x
    tx = tile - ty * tiles_x
    px0 = tx * TILE
    py0 = ty * TILE
    px1 = min(px0 + TILE, width) - 1
    py1 = min(py0 + TILE, height) - 1
    start = tile_offsets[tile]
    end = tile_offsets[tile + 1]
    n_max = 0
    for y in range(py0, py1 + 1):
        for x in range(px0, px1 + 1):
            scratch[y, x, 0] = final_trans[y, x]
            scratch[y, x, 1] = 0.0
            scratch[y, x, 2] = 0.0
            scratch[y, x, 3] = 0.0
            scratch[y, x, 4] = 0.0
            n_max = max(n_max, last[y, x])
    for k in range(start + n_max, end):
        row = entry_slot[k]
        for c in range(slot_grads.shape[1]):
            slot_grads[row, c] = 0.0
    bg0 = background[0]
    bg1 = background[1]
    bg2 = background[2]
    for k in range(start + n_max - 1, start - 1, -1):
        kk = k - start
        mx = tile_rec[k, MX] * 1.0
        my = tile_rec[k, MY] * 1.0
        ca = tile_rec[k, CA] * 1.0
        cb = tile_rec[k, CB] * 1.0
        cc = tile_rec[k, CC] * 1.0
        op = tile_rec[k, OPAC] * 1.0
        cr = tile_rec[k, RED] * 1.0
        cg = tile_rec[k, GREEN] * 1.0
        cbl = tile_rec[k, BLUE] * 1.0
        z = tile_rec[k, DEPTH] * 1.0
        pmin = tile_rec[k, POWER_MIN] * 1.0
        maha2 = tile_rec[k, MAHA2] * 1.0
        g_mx = 0.0
        g_my = 0.0
        g_ca = 0.0
        g_cb = 0.0
        g_cc = 0.0
        g_r = 0.0
        g_g = 0.0
        g_b = 0.0
        g_op = 0.0
        g_z = 0.0
        ya, yb = _row_range(my, tile_rec[k, EXT_Y] * 1.0, py0, py1)
        for y in range(ya, yb + 1):
            dy = my - y
            xa, xb = _col_span(mx, dy, ca, cb, cc, maha2, px0, px1)
            for x in range(xa, xb + 1):
                if kk >= last[y, x]:
                    continue
                dx = mx - x
                power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                if not (power >= pmin):
                    continue
                gauss = math.exp(power)
                a_raw = op * gauss
                alpha = min(ALPHA_MAX, a_raw)
                inv_om = 1.0 / (1.0 - alpha)
                t_before = scratch[y, x, 0] * inv_om
                w = alpha * t_before
                vr = v_color[y, x, 0] * 1.0
                vg = v_color[y, x, 1] * 1.0
                vb = v_color[y, x, 2] * 1.0
                vd = v_depth[y, x] * 1.0
                g_r += w * vr
                g_g += w * vg
                g_b += w * vb
                g_z += w * vd
                tf = final_trans[y, x]
                behind_r = scratch[y, x, 1]
                behind_g = scratch[y, x, 2]
                behind_b = scratch[y, x, 3]
                behind_d = scratch[y, x, 4]
                # d(out)/d(alpha): own colour times transmittance in front, minus everything
                # behind (background included) divided by (1 - alpha).
                v_a = (
                    (cr * t_before - (behind_r + tf * bg0) * inv_om) * vr
                    + (cg * t_before - (behind_g + tf * bg1) * inv_om) * vg
                    + (cbl * t_before - (behind_b + tf * bg2) * inv_om) * vb
                    + (z * t_before - behind_d * inv_om) * vd
                    + v_alpha[y, x] * tf * inv_om
                )
                scratch[y, x, 0] = t_before
                scratch[y, x, 1] = behind_r + w * cr
                scratch[y, x, 2] = behind_g + w * cg
                scratch[y, x, 3] = behind_b + w * cbl
                scratch[y, x, 4] = behind_d + w * z
                if a_raw < ALPHA_MAX:
                    g_op += gauss * v_a
                    v_pow = a_raw * v_a
                    g_mx -= v_pow * (ca * dx + cb * dy)
                    g_my -= v_pow * (cb * dx + cc * dy)
                    g_ca -= 0.5 * v_pow * dx * dx
                    g_cb -= v_pow * dx * dy
                    g_cc -= 0.5 * v_pow * dy * dy
        row = entry_slot[k]
        slot_grads[row, G_MX] = g_mx
        slot_grads[row, G_MY] = g_my
        slot_grads[row, G_CA] = g_ca
        slot_grads[row, G_CB] = g_cb
        slot_grads[row, G_CC] = g_cc
        slot_grads[row, G_RED] = g_r
        slot_grads[row, G_GREEN] = g_g
        slot_grads[row, G_BLUE] = g_b
        slot_grads[row, G_OPAC] = g_op
        slot_grads[row, G_DEPTH] = g_z


@njit(nogil=True, cache=True)
def composite_backward(
    lo, hi, tile_rec, tile_offsets, tile_order, tiles_x, width, height, background,
    final_trans, last, v_color, v_alpha, v_depth, entry_slot, scratch, slot_grads,
):
    """Replay each pixel back to front from its last contributor and write per-slot gradients.

    v_color (H, W, 3), v_alpha (H, W) and v_depth (H, W) are the upstream gradients of colour,
    alpha = 1 - final_trans and the alpha-weighted depth sum. scratch (H, W, 5) holds per pixel the
    running transmittance and the colour/depth accumulated behind the current Gaussian.
    slot_grads (M, GRAD_WIDTH): row entry_slot[k] gets the summed gradient of tile entry k.

    Handles tiles tile_order[lo:hi] and releases the GIL. Tiles own their pixels and slots, so
    chunks on different threads never write the same memory.
    """
    for oi in range(lo, hi):
        _composite_backward_tile(
            tile_order[oi],
            tile_rec, tile_offsets, tile_order, tiles_x, width, height, background,
            final_trans, last, v_color, v_alpha, v_depth, entry_slot, scratch, slot_grads,
        )
