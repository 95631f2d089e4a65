"""Maps a remote clock (a board's sample counter, a MoCap server's time) onto the host clock.

Input: pairs (remote time, host arrival time), both in ns. The arrival is the remote event plus
a transport delay that is never negative and often larger than usual (a loaded host, a queued
packet), never smaller. So the host time of a remote instant is estimated on the *lower
envelope* of ``arrival - remote``:

- rate (drift): a least-squares line through the minima of ``arrival - remote`` over blocks of
  remote time (``block_s``, the last ``blocks`` of them): one sample per block, a delay spike
  never reaches a block's minimum unless it lasts the whole block;
- offset: the running minimum of the residual against that line, raised by a slow leak
  (``leak_ppm`` of the elapsed remote time) so that it follows a drift the line has not learnt
  yet and a transport that became slower for good.

The mapped time of a sample is therefore never later than its arrival (sample ages are never
negative); it is the arrival minus the delay above the smallest delay seen, i.e. the smallest
delay itself is not observable from one-way stamps (a configured constant adds it back).

A remote clock that steps (a board that restarted its counter, a server whose clock was set)
is re-learnt: a residual below the envelope by more than ``step_s`` at once, or above it for
``step_confirm`` samples in a row spanning ``step_confirm_s`` of remote time, with an excess
that stayed put (a host that stalled delivers a burst of late samples whose excess shrinks as
the burst catches up: not a step); the rate learnt so far is kept (the crystal did not
change).

O(1) per sample with no allocation except the block fit (once per block, ``blocks`` points).
Pure: no clock of its own, no threads; the caller owns locking.
"""

from __future__ import annotations

import math

__all__ = ["ClockSync"]


class ClockSync:
    """Host-clock estimate of a remote clock, from (remote ns, arrival ns) pairs."""

    __slots__ = (
        "_above", "_above_e", "_above_since", "_blk_d", "_blk_end", "_blk_len", "_blk_r",
        "_block_ns", "_leak",
        "_n_pts", "_o", "_pt_d", "_pt_i", "_pt_r", "_ref_r", "_s", "_s_sigma", "_step_confirm",
        "_step_confirm_ns", "_step_ns", "last_remote_ns", "samples", "steps",
    )

    def __init__(self, *, block_s: float = 0.5, blocks: int = 32, leak_ppm: float = 50.0,
                 step_s: float = 0.05, step_confirm: int = 16,
                 step_confirm_s: float = 2.0) -> None:
        if not (block_s > 0.0 and blocks >= 2 and leak_ppm >= 0.0 and step_s > 0.0
                and step_confirm >= 1):
            raise ValueError("ClockSync: block_s > 0, blocks >= 2, leak_ppm >= 0, step_s > 0, "
                             "step_confirm >= 1")
        self._block_ns = round(block_s * 1e9)
        self._leak = leak_ppm * 1e-6
        self._step_ns = step_s * 1e9
        self._step_confirm = step_confirm
        self._step_confirm_ns = round(step_confirm_s * 1e9)
        self._above_since = 0
        self._above_e = 0.0
        self._pt_r = [0] * blocks  # remote time of each block minimum (ring)
        self._pt_d = [0] * blocks  # arrival - remote at that minimum
        self._pt_i = 0
        self._n_pts = 0
        self._s = 0.0  # host ns per remote ns, minus 1
        self._s_sigma = math.inf  # standard error of _s from the fit's residuals
        self._ref_r = 0  # remote time the line is referred to
        self._o = 0.0  # envelope offset: host - remote - s * (remote - ref) (ns)
        self._above = 0
        self._blk_end = 0
        self._blk_len = 0
        self._blk_r = 0
        self._blk_d = 0
        self.last_remote_ns = 0
        self.samples = 0
        self.steps = 0

    # ------------------------------------------------------------------ estimate

    def update(self, remote_ns: int, arrival_ns: int) -> int:
        """Add one pair; the host time of ``remote_ns`` (never later than ``arrival_ns``)."""
        d = arrival_ns - remote_ns
        if self.samples == 0:
            self._restart(remote_ns, d)
            self.samples = 1
            return arrival_ns
        self.samples += 1
        dr = remote_ns - self.last_remote_ns
        e = d - self._s * (remote_ns - self._ref_r)
        o = self._o + self._leak * dr if dr > 0 else self._o
        if e < o - self._step_ns:
            self.steps += 1
            self._restart(remote_ns, d)
            return arrival_ns
        if e > o + self._step_ns:
            # a delay spike, or the remote clock stepped back: held until it persists
            # the confirmation restarts whenever the excess drops by a quarter step below where
            # it started: a catching-up burst keeps dropping, a real step stays put
            excess = e - o
            if self._above == 0 or excess < self._above_e - self._step_ns / 4:
                self._above_since = remote_ns
                self._above_e = excess
            self._above += 1
            if (self._above >= self._step_confirm
                    and remote_ns - self._above_since >= self._step_confirm_ns):
                self.steps += 1
                self._restart(remote_ns, d)
                return arrival_ns
        else:
            self._above = 0
            if e < o:
                o = e
            if d < self._blk_d or self._blk_len == 0:
                self._blk_r, self._blk_d = remote_ns, d
            self._blk_len += 1
        self._o = o
        self.last_remote_ns = remote_ns
        if remote_ns >= self._blk_end and self._blk_len:
            self._close_block(remote_ns)
        t = round(remote_ns + self._s * (remote_ns - self._ref_r) + self._o)
        return t if t <= arrival_ns else arrival_ns

    def map(self, remote_ns: int) -> int:
        """Host time of any remote instant on the current estimate (no update)."""
        return round(remote_ns + self._s * (remote_ns - self._ref_r) + self._o)

    # ------------------------------------------------------------------ readings

    @property
    def rate_ratio(self) -> float:
        """Host seconds per remote second (1.012 for a remote clock 1.2 % slow)."""
        return 1.0 + self._s

    @property
    def drift_ppm(self) -> float:
        """Rate error of the remote clock against the host's, ppm (negative: it runs slow)."""
        return (1.0 / (1.0 + self._s) - 1.0) * 1e6

    @property
    def offset_ns(self) -> int:
        """Host time minus remote time at the newest sample (includes the smallest delay)."""
        r = self.last_remote_ns
        return self.map(r) - r

    @property
    def drift_sigma_ppm(self) -> float:
        """Standard error of :attr:`drift_ppm` (inf until three blocks): the larger of the
        scatter of the block minima about the fitted line and the jackknife of the slope, so a
        trend that is not a rate (a start-up delay that shrinks) widens it. Early on it is the
        transport's jitter over a short baseline; it shrinks as the baseline grows."""
        return self._s_sigma * 1e6

    @property
    def rate_known(self) -> bool:
        """True once at least two blocks have given the rate."""
        return self._n_pts >= 2

    # ------------------------------------------------------------------ internals

    def _restart(self, remote_ns: int, d: int) -> None:
        self._ref_r = remote_ns
        self._o = float(d)
        self._above = 0
        self._s_sigma = math.inf
        self._n_pts = 0
        self._pt_i = 0
        self.last_remote_ns = remote_ns
        # the first blocks are short so that a large rate error is learnt within ~1 s
        self._blk_len = 1
        self._blk_r, self._blk_d = remote_ns, d
        self._blk_end = remote_ns + max(self._block_ns // 8, 1)

    def _close_block(self, remote_ns: int) -> None:
        size = len(self._pt_r)
        self._pt_r[self._pt_i] = self._blk_r
        self._pt_d[self._pt_i] = self._blk_d
        self._pt_i = (self._pt_i + 1) % size
        self._n_pts = min(self._n_pts + 1, size)
        self._blk_len = 0
        length = min(self._block_ns, max(self._block_ns // 8, 1) << min(self._n_pts, 3))
        self._blk_end = remote_ns + length
        if self._n_pts < 2:
            return
        n = self._n_pts
        start = (self._pt_i - n) % size
        r0, d0 = self._pt_r[start], self._pt_d[start]
        sr = sd = srr = srd = 0.0
        for k in range(n):
            j = (start + k) % size
            x = float(self._pt_r[j] - r0)
            y = float(self._pt_d[j] - d0)
            sr += x
            sd += y
            srr += x * x
            srd += x * y
        den = n * srr - sr * sr
        if den <= 0.0:
            return
        s_new = (n * srd - sr * sd) / den
        if not math.isfinite(s_new) or abs(s_new) > 0.1:
            return
        if n > 2:
            c = (sd - s_new * sr) / n
            sse = 0.0
            for k in range(n):
                j = (start + k) % size
                res = (self._pt_d[j] - d0) - c - s_new * (self._pt_r[j] - r0)
                sse += res * res
            sigma = math.sqrt(sse / (n - 2) / (srr - sr * sr / n))
            # the jackknife of the slope (leave each minimum out in turn) as well: the fit's
            # residuals only measure scatter, and a trend that is not a rate (the first
            # samples of a stream stamped late by a host still starting up, their delay
            # shrinking) bends the line with small residuals. Leaving the late minimum out
            # moves the slope by about that bias, so the error bar covers it.
            loo_sum = loo_sq = 0.0
            m = n - 1
            for k in range(n):
                j = (start + k) % size
                x = float(self._pt_r[j] - r0)
                y = float(self._pt_d[j] - d0)
                sr_k, sd_k = sr - x, sd - y
                den_k = m * (srr - x * x) - sr_k * sr_k
                if den_k <= 0.0:
                    break
                s_k = (m * (srd - x * y) - sr_k * sd_k) / den_k
                loo_sum += s_k
                loo_sq += s_k * s_k
            else:
                spread = max(loo_sq - loo_sum * loo_sum / n, 0.0)
                sigma = max(sigma, math.sqrt(spread * (n - 1) / n))
            self._s_sigma = sigma
        # re-refer the line to now, on the lowest block minimum under the new slope (the
        # running minimum then only has to follow what changed within one block)
        o = math.inf
        for k in range(n):
            j = (start + k) % size
            o = min(o, self._pt_d[j] - s_new * (self._pt_r[j] - remote_ns))
        self._o = o
        self._ref_r = remote_ns
        self._s = s_new
