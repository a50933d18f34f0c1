"""A Kalman filter and Rauch-Tung-Striebel smoother for 3D keypoint tracks (numpy), offline and causal.

Each keypoint is a point moving at constant velocity (``model="velocity"``: state position and velocity) or
constant acceleration (``"acceleration"``) driven by white noise of standard deviation ``q`` (world units per
frame squared, or cubed). It is measured, frame by frame, as the triangulated point with an isotropic
standard deviation ``s * std[t, k]``: ``std`` comes from the detection (its confidence and reprojection
residual, :func:`s3k.inference.track_filter.measurement_std`), ``s`` is a scale. The three axes share one
covariance, so the filter runs on arrays over every keypoint (and every candidate ``(q, s)``) at once: one
numpy step per frame whatever the number of keypoints, where a per-keypoint filter object (filterpy) would
loop over keypoints and frames in Python.

- **Outliers in time.** A measurement whose innovation (the distance between the measured and the predicted
  point, in units of its predicted standard deviation) exceeds ``gate`` is rejected: the filter does not
  take it and the frame is marked. Rejections count as missing frames.
- **Gaps.** A keypoint missing (or rejected) for up to ``max_gap`` frames is bridged by the model; after a
  longer gap the filter starts again at the next measurement (a new segment: the smoother does not join
  segments, and frames between them stay empty).
- **Noise.** ``q`` and ``s`` default to the values that maximise the (robust) likelihood of the track's own
  measurements, per keypoint, over a grid (:func:`fit_noise`): no tuning by hand, as the ensemble Kalman
  smoother fits its smoothing parameter. A rejected measurement costs a constant, so outliers cannot drive
  the fit.
- **Offline** (:func:`smooth`): the forward filter, then the RTS smoother over each segment, so each frame's
  point uses the frames before and after it. **Causal** (:class:`CausalFilter`): the forward filter only,
  one frame at a time, its noise fitted on the frames seen so far; the output at frame ``t`` depends on no
  frame after ``t``.
"""

from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from s3k.base.choices import FilterMethod, MotionModel
from s3k.base.ranges import Range

__all__ = ["MODELS", "RANGES", "CausalFilter", "FilterSettings", "Smoothed", "fit_noise", "forward", "smooth"]

MODELS = {"velocity": 2, "acceleration": 3}
"""The motion models and the size of their state per axis."""

#: Measurements rejected in a row after which the filter starts again at the next one (it has lost the point).
LOST = 3
#: The outliers' share and the width of the region they fall in, in robust sizes of the track's second
#: differences: a rejected measurement costs the log-density of that uniform outlier model.
OUTLIER_SHARE = 0.01
OUTLIER_WIDTH = 20.0

#: Frames of history at which :class:`CausalFilter` fits its noise again (then every ``REFIT_LAST`` frames).
REFIT_AT = (16, 32, 64, 128, 256)
REFIT_LAST = 256

#: The range of each numeric setting of :class:`FilterSettings` (the command line's ``--filter-...`` options
#: declare the same): bounds within which the squares and products of the filter stay finite and above zero.
#: A gate of 100 standard deviations rejects nothing a real track holds (0 turns it off); deviations in world
#: units span a micrometre to a kilometre in millimetres or metres; the fitted noise scales lie in 1/64 to 8.
RANGES = {
    "gate": Range(ge=0, le=100),
    "process_noise": Range(ge=1e-6, le=1e6),
    "noise_scale": Range(ge=1e-3, le=1e3),
    "noise_px": Range(ge=0, le=1e4),
    "layout_std": Range(ge=1e-6, le=1e6),
    "limb_std": Range(ge=1e-6, le=1e6),
    "max_gap": Range(ge=0),
}


@dataclass
class FilterSettings:
    """How a track is filtered (``s3k track --filter ...``, ``s3k stream --filter ...``).

    Attributes:
        method: ``"kalman"`` or ``"none"``.
        model: ``"velocity"`` (constant velocity) or ``"acceleration"`` (constant acceleration).
        process_noise: ``q``, the standard deviation of the white noise driving the motion, world units per
            frame squared (velocity model) or cubed; None: fitted per keypoint.
        noise_scale: ``s``, the scale of the measurement noise; None: fitted per keypoint.
        noise_px: the least reprojection residual a detection counts with, pixels; None: the keypoint's median
            residual over the track.
        gate: innovation gate in standard deviations (0: no rejection).
        max_gap: the longest run of missing or rejected frames that is bridged.
        rigid: hold the keypoints to the run's rigid layout (None: when the run has one).
        layout_std: how far, world units, a keypoint may stand off the rigid layout (None: fitted from the
            track).
        limb_std: how far a limb's length may stand off its median length, world units (None: fitted per
            limb from the track).
    """

    method: FilterMethod = "kalman"
    model: MotionModel = "velocity"
    process_noise: float | None = None
    noise_scale: float | None = None
    noise_px: float | None = None
    gate: float = 4.0
    max_gap: int = 10
    rigid: bool | None = None
    layout_std: float | None = None
    limb_std: float | None = None

    def check(self) -> FilterSettings:
        """Raise a :class:`UserError` naming the option of a value out of its range; returns ``self`` (the
        method and model are :data:`s3k.base.choices.FilterMethod` and ``MotionModel``, checked where text
        becomes them: :class:`s3k.inference.track_config.TrackConfig`)."""
        for name, bounds in RANGES.items():
            value = getattr(self, name)
            if value is not None:
                bounds.check(value, f"--filter-{name.replace('_', '-')}")
        return self

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def nanmedian(a: np.ndarray) -> np.ndarray:
    """The median over the first axis of the finite values (NaN where there is none), without warnings."""
    a = np.where(np.isfinite(a), a, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(a, axis=0)


def _matrices(model: MotionModel) -> tuple[np.ndarray, np.ndarray]:
    """``(F, Q1)``: the transition over one frame and the process noise for ``q = 1`` (continuous white noise
    integrated over the frame)."""
    if model == "velocity":
        return np.array([[1.0, 1.0], [0.0, 1.0]]), np.array([[1 / 3, 1 / 2], [1 / 2, 1.0]])
    F = np.array([[1.0, 1.0, 0.5], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]])
    Q = np.array([[1 / 20, 1 / 8, 1 / 6], [1 / 8, 1 / 3, 1 / 2], [1 / 6, 1 / 2, 1.0]])
    return F, Q


@dataclass
class _State:
    """The filter's state over leading dims ``L`` (candidates x keypoints): mean ``m (*L, 3, n)``,
    covariance ``P (*L, n, n)`` shared by the axes, ``init (*L)`` whether a segment has started, ``gap (*L)``
    frames since the last measurement taken, ``count (*L)`` measurements taken in the segment, ``miss (*L)``
    measurements rejected in a row."""

    m: np.ndarray
    P: np.ndarray
    init: np.ndarray
    gap: np.ndarray
    count: np.ndarray
    miss: np.ndarray

    @classmethod
    def empty(cls, shape: tuple[int, ...], n: int) -> _State:
        return cls(np.zeros((*shape, 3, n)), np.tile(np.eye(n), (*shape, 1, 1)), np.zeros(shape, bool),
                   np.zeros(shape, np.int64), np.zeros(shape, np.int64), np.zeros(shape, np.int64))


@dataclass
class _Step:
    """One frame of the forward pass: the prediction (``m_p``, ``P_p``), the state after the frame, what was
    done with the measurement (``taken``, ``rejected``, ``restart``: a new segment starts here) and the
    robust negative log-likelihood of it (``cost``)."""

    m_p: np.ndarray
    P_p: np.ndarray
    state: _State
    taken: np.ndarray
    rejected: np.ndarray
    restart: np.ndarray
    cost: np.ndarray


def _step(state: _State, z: np.ndarray, r: np.ndarray, q: np.ndarray, settings: FilterSettings,
          FQ: tuple[np.ndarray, np.ndarray], floor: np.ndarray, force: np.ndarray | bool = False) -> _Step:
    """One frame: predict, gate, update (or start a segment). ``z (K, 3)`` the measurement (NaN: missing),
    ``r (*L)`` its variance, ``q (*L)`` the process noise, ``floor (*L)`` the cost of a rejection; ``force``
    starts a segment at the measurement. A segment also starts after ``max_gap`` frames without a
    measurement taken, and after ``LOST`` measurements rejected in a row (the filter has lost the point)."""
    F, Q1 = FQ
    n = F.shape[0]
    m_p = np.einsum("...an,mn->...am", state.m, F)
    P_p = F @ state.P @ F.T + (q**2)[..., None, None] * Q1
    seen = np.isfinite(z).all(-1) & np.isfinite(r)
    S = P_p[..., 0, 0] + r
    y = np.nan_to_num(z) - m_p[..., 0]
    d2 = (y**2).sum(-1) / S
    restart = seen & (~state.init | (state.gap >= settings.max_gap) | (state.miss >= LOST) | force)
    live = seen & ~restart
    # no gate until the segment's first n measurements have placed its velocity (and acceleration)
    rejected = live & (settings.gate > 0) & (d2 > settings.gate**2) & (state.count >= n)
    taken = live & ~rejected
    gain = P_p[..., :, 0] / S[..., None]  # (*L, n)
    m_u = m_p + y[..., None] * gain[..., None, :]
    P_u = P_p - gain[..., :, None] * P_p[..., None, 0, :]
    m_r = np.zeros_like(m_p)
    m_r[..., 0] = np.nan_to_num(z)
    prior = np.concatenate([r[..., None], np.broadcast_to(1e4 * (r + q**2)[..., None], (*r.shape, n - 1))],
                           -1)
    P_r = prior[..., None] * np.eye(n)
    m = np.where(taken[..., None, None], m_u, np.where(restart[..., None, None], m_r, m_p))
    P = np.where(taken[..., None, None], P_u, np.where(restart[..., None, None], P_r, P_p))
    init = state.init | restart
    gap = np.where(taken | restart, 0, state.gap + 1)
    count = np.where(restart, 1, state.count + taken)
    miss = np.where(rejected, state.miss + 1, np.where(taken | restart, 0, state.miss))
    nll = 0.5 * d2 + 1.5 * np.log(2 * np.pi * S)
    settled = state.count >= n  # the first measurements of a segment place it: they cost nothing
    cost = np.where(taken & settled, np.minimum(nll, floor), np.where(rejected, floor, 0.0))
    return _Step(m_p, P_p, _State(m, P, init, gap, count, miss), taken, rejected, restart, cost)


def _floor(X: np.ndarray) -> np.ndarray:
    """``(K,)`` the cost of a rejected measurement: the negative log-density of an outlier, a share
    ``OUTLIER_SHARE`` spread uniformly over a cube ``OUTLIER_WIDTH`` robust second differences wide. It does
    not depend on the noise being fitted, so rejecting cannot make a small noise look likely."""
    return -np.log(OUTLIER_SHARE) + 3 * np.log(OUTLIER_WIDTH * _base_scale(X))


@dataclass
class Forward:
    """The forward pass over a track: per frame ``m_f (T, *L, 3, n)``, ``P_f``, the predictions ``m_p``,
    ``P_p`` and the flags ``taken``, ``rejected``, ``restart``, ``init`` and ``gap`` ``(T, *L)``; ``cost`` the
    robust negative log-likelihood summed over the frames ``(*L)``."""

    m_f: np.ndarray
    P_f: np.ndarray
    m_p: np.ndarray
    P_p: np.ndarray
    taken: np.ndarray
    rejected: np.ndarray
    restart: np.ndarray
    init: np.ndarray
    gap: np.ndarray
    cost: np.ndarray


def forward(X: np.ndarray, std: np.ndarray, q: np.ndarray, s: np.ndarray, settings: FilterSettings,
            keep: bool = True, force: np.ndarray | None = None) -> Forward:
    """The forward filter over a track ``X (T, K, 3)`` (NaN: missing) with measurement standard deviations
    ``std (T, K)``, for every candidate ``q``, ``s`` of shape ``(*G, K)`` at once (``keep=False``: only the
    cost, without the per-frame arrays)."""
    X, std = np.asarray(X, np.float64), np.asarray(std, np.float64)
    q, s = np.broadcast_arrays(np.asarray(q, np.float64), np.asarray(s, np.float64))
    FQ = _matrices(settings.model)
    n = FQ[0].shape[0]
    state = _State.empty(q.shape, n)
    floor = np.broadcast_to(_floor(X), q.shape)
    steps: list[_Step] = []
    cost = np.zeros(q.shape)
    for t in range(len(X)):
        st = _step(state, X[t], (s * std[t]) ** 2, q, settings, FQ, floor,
                   False if force is None else force[t])
        cost += st.cost
        state = st.state
        if keep:
            steps.append(st)
    if not keep:
        return Forward(*(np.zeros(0),) * 9, cost)  # type: ignore[arg-type]

    def stack(get) -> np.ndarray:
        return np.stack([get(st) for st in steps]) if steps else np.zeros((0, *q.shape))

    return Forward(stack(lambda st: st.state.m), stack(lambda st: st.state.P), stack(lambda st: st.m_p),
                   stack(lambda st: st.P_p), stack(lambda st: st.taken), stack(lambda st: st.rejected),
                   stack(lambda st: st.restart), stack(lambda st: st.state.init),
                   stack(lambda st: st.state.gap), cost)


def _base_scale(X: np.ndarray) -> np.ndarray:
    """``(K,)`` a robust size of each keypoint's frame-to-frame second difference, the scale of the process
    noise grid (1e-3 where it cannot be measured)."""
    d2 = np.linalg.norm(X[2:] - 2 * X[1:-1] + X[:-2], axis=-1) if len(X) > 2 else np.zeros((0, X.shape[1]))
    med = nanmedian(d2) if len(d2) else np.full(X.shape[1], np.nan)
    return np.where(np.isfinite(med) & (med > 0), med, 1e-3)


Q_GRID = 2.0 ** np.arange(-10.0, 5.0)
S_GRID = 2.0 ** np.arange(-6.0, 4.0)


def fit_noise(X: np.ndarray, std: np.ndarray, settings: FilterSettings) -> tuple[np.ndarray, np.ndarray]:
    """``(q (K,), s (K,))``: the settings' values where given, else the grid values that maximise each
    keypoint's robust likelihood of the track's measurements (module docstring)."""
    K = X.shape[1]
    base = _base_scale(X)
    if settings.model == "acceleration":
        qs = np.concatenate([Q_GRID * 2.0**-4, Q_GRID[-4:]])
    else:
        qs = Q_GRID
    qg = (np.full((1, K), settings.process_noise) if settings.process_noise is not None
          else qs[:, None] * base[None])  # (Gq, K)
    sg = (np.full((1, K), settings.noise_scale) if settings.noise_scale is not None else S_GRID[:, None]
          * np.ones((1, K)))
    q = np.broadcast_to(qg[:, None], (len(qg), len(sg), K))
    s = np.broadcast_to(sg[None], (len(qg), len(sg), K))
    cost = forward(X, std, q, s, settings, keep=False).cost.reshape(-1, K)
    best = np.argmin(cost, axis=0)
    return q.reshape(-1, K)[best, np.arange(K)], s.reshape(-1, K)[best, np.arange(K)]


@dataclass
class Smoothed:
    """A filtered track: ``X (T, K, 3)`` (NaN where not placed), ``var (T, K)`` the variance of each
    coordinate, ``valid``, ``measured`` (a measurement was taken), ``rejected`` (the gate rejected it) and
    ``bridged`` (placed without a measurement) ``(T, K)``; the noise used, ``q (K,)`` and ``s (K,)``."""

    X: np.ndarray
    var: np.ndarray
    valid: np.ndarray
    measured: np.ndarray
    rejected: np.ndarray
    bridged: np.ndarray
    q: np.ndarray
    s: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)


def _lost_starts(rejected: np.ndarray) -> np.ndarray:
    """``(T, K)`` the first frame of every run of at least ``LOST`` rejections in consecutive frames."""
    out = np.zeros_like(rejected)
    for k in range(rejected.shape[1]):
        idx = np.flatnonzero(rejected[:, k])
        if len(idx) < LOST:
            continue
        breaks = np.flatnonzero(np.diff(idx) > 1) + 1
        for run in np.split(idx, breaks):
            if len(run) >= LOST:
                out[run[0], k] = True
    return out


def smooth(X: np.ndarray, std: np.ndarray, settings: FilterSettings) -> Smoothed:
    """The offline smoother (module docstring): noise fitted (unless given), forward filter, RTS smoother
    over each segment. Frames between a segment's first and last measurement are placed (a missing or
    rejected frame inside one is bridged), and so is a rejected frame after the last one."""
    X = np.asarray(X, np.float64)
    q, s = fit_noise(X, std, settings)
    fw = forward(X, std, q, s, settings)
    force = np.zeros(X.shape[:2], bool)
    for _ in range(10):  # a point lost: the segment starts again at the first measurement it rejected
        starts = _lost_starts(fw.rejected) & ~force
        if not starts.any():
            break
        force |= starts
        fw = forward(X, std, q, s, settings, force=force)
    T = len(X)
    F = _matrices(settings.model)[0]
    m_s, P_s = fw.m_f.copy(), fw.P_f.copy()
    for t in range(T - 2, -1, -1):
        C = fw.P_f[t] @ F.T @ np.linalg.inv(fw.P_p[t + 1])  # (K, n, n)
        join = fw.init[t] & ~fw.restart[t + 1]
        m = fw.m_f[t] + np.einsum("kij,kaj->kai", C, m_s[t + 1] - fw.m_p[t + 1])
        P = fw.P_f[t] + C @ (P_s[t + 1] - fw.P_p[t + 1]) @ np.swapaxes(C, -1, -2)
        m_s[t] = np.where(join[:, None, None], m, fw.m_f[t])
        P_s[t] = np.where(join[:, None, None], P, fw.P_f[t])
    measured = fw.taken | fw.restart
    # placed: a measurement of the same segment at or after the frame (none is skipped by a restart)
    ahead = np.zeros_like(measured)
    nxt = np.zeros(X.shape[1], bool)
    for t in range(T - 1, -1, -1):
        nxt = measured[t] | (nxt & ~(fw.restart[t + 1] if t + 1 < T else False))
        ahead[t] = nxt
    seen = np.isfinite(X).all(-1)  # a frame with a point of its own keeps one, rejected or not
    valid = fw.init & (ahead | (seen & (fw.gap <= settings.max_gap)))
    out = np.where(valid[..., None], m_s[..., 0], np.nan) if T else np.zeros_like(X)
    var = np.where(valid, P_s[..., 0, 0], np.nan) if T else np.zeros(X.shape[:2])
    return Smoothed(out, var, valid, measured, fw.rejected, valid & ~measured, q, s)


class CausalFilter:
    """The forward filter one frame at a time (module docstring): ``filter(X (K, 3), std (K,))`` gives the
    frame's ``(X (K, 3), valid (K,), rejected (K,))`` from it and the frames before it only. A keypoint is
    placed from its first measurement on, predicted through gaps of up to ``max_gap`` frames. The noise not
    given in ``settings`` is fitted on the frames seen so far after ``REFIT_AT`` frames, then every
    ``REFIT_LAST`` frames on the last ``REFIT_LAST``; before the first fit the measurements are taken at
    their own noise (``s = 1``) with the process noise of their second differences."""

    def __init__(self, num_keypoints: int, settings: FilterSettings) -> None:
        self.settings = settings
        self.K = num_keypoints
        self.FQ = _matrices(settings.model)
        self.state = _State.empty((num_keypoints,), self.FQ[0].shape[0])
        self.history: list[tuple[np.ndarray, np.ndarray]] = []
        self.q = np.full(num_keypoints, np.nan)
        self.s = np.full(num_keypoints, settings.noise_scale or 1.0)
        self.fitted = False
        self.seen = 0

    def _noise(self) -> None:
        """Fit the noise on the history at the frames the class docstring names; before the first fit, the
        process noise of the second differences seen so far."""
        n = self.seen
        if n in REFIT_AT or (n > REFIT_AT[-1] and (n - REFIT_AT[-1]) % REFIT_LAST == 0):
            X = np.stack([h[0] for h in self.history])
            std = np.stack([h[1] for h in self.history])
            self.q, self.s = fit_noise(X, std, self.settings)
            self.fitted = True
        elif not self.fitted:
            X = np.stack([h[0] for h in self.history])
            self.q = (np.full(self.K, self.settings.process_noise) if self.settings.process_noise is not None
                      else _base_scale(X))

    def __call__(self, X: np.ndarray, std: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        X, std = np.asarray(X, np.float64), np.asarray(std, np.float64)
        self.history.append((X, std))
        del self.history[:-REFIT_LAST]
        self.seen += 1
        self._noise()
        floor = _floor(np.stack([h[0] for h in self.history]))
        st = _step(self.state, X, (self.s * std) ** 2, self.q, self.settings, self.FQ, floor)
        self.state = st.state
        valid = st.state.init & (st.state.gap <= self.settings.max_gap)
        return np.where(valid[:, None], st.state.m[..., 0], np.nan), valid, st.rejected
