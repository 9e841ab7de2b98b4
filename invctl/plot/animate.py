"""Animations and snapshots of planar mechanisms from a time history of ``q``.

A scene declares what to draw once, symbolically, as a :class:`Drawing`: named
points (2-vectors in the model's ``q`` and parameter symbols) and links between
them.  :func:`animate` evaluates all points for all frames in one mapped CasADi
call and writes a GIF (Pillow) or MP4 (ffmpeg); :func:`snapshot` overlays a few
poses in one image.  Figures are made on the Agg canvas directly (no pyplot
state is touched, nothing is left open).
"""
from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import casadi as ca
import numpy as np

from ..errors import AnimationError, DimensionError, DrawingError, ParameterError, SceneError
from ..scenes import Scene, _is_path, load_scene

LINK_STYLE = {"color": "tab:blue", "lw": 3.0, "solid_capstyle": "round"}
POINT_STYLE = {"marker": "o", "ms": 5.0, "color": "k", "ls": "none"}
SEGMENT_STYLE = {"color": "0.35", "lw": 2.0}
TRAIL_STYLE = {"lw": 1.0, "alpha": 0.8}


def _style(style, where: str) -> dict:
    if style is None:
        return {}
    if not isinstance(style, Mapping) or not all(isinstance(k, str) for k in style):
        raise DrawingError(f"{where}: a style is a dict of matplotlib line properties, got {style!r}")
    return dict(style)


def _merged(default: Mapping, style: Mapping) -> dict:
    """``default`` updated by ``style``, aliases (``lw``/``linewidth``, ...) resolved to one name."""
    from matplotlib import cbook, lines

    return {**cbook.normalize_kwargs(dict(default), lines.Line2D), **cbook.normalize_kwargs(dict(style), lines.Line2D)}


@dataclass(frozen=True, eq=False)
class Drawing:
    """What to draw of a planar mechanism.

    Parameters
    ----------
    points : dict[str, casadi.SX]
        Name -> position ``(x, y)`` as an expression in ``model.q`` and ``model.theta``.
    links : sequence of ``(a, b)`` or ``(a, b, style)``
        Line segments between named points; ``style`` is a dict of matplotlib line
        properties (default :data:`LINK_STYLE`).
    segments : sequence of ``((x0, y0), (x1, y1))`` or ``(p0, p1, style)``
        Fixed elements: ground line, walls (default :data:`SEGMENT_STYLE`).
    limits : ``((xmin, xmax), (ymin, ymax))``, optional
        Axis limits; by default from the whole motion and the fixed elements.
    point_style : dict, optional
        Marker style of the points (default :data:`POINT_STYLE`); ``{}`` hides them.
    axis_labels : (str, str)
        Labels of the drawing's horizontal and vertical axes, with units.
    """

    points: Mapping[str, Any]
    links: Sequence[tuple] = ()
    segments: Sequence[tuple] = ()
    limits: tuple | None = None
    point_style: Mapping[str, Any] | None = None
    axis_labels: tuple = ("x [m]", "y [m]")
    _sx: ca.SX = field(init=False, repr=False)

    def __post_init__(self):
        if not isinstance(self.points, Mapping) or not self.points:
            raise DrawingError("Drawing.points must be a non-empty dict name -> 2-vector expression")
        pts = {}
        for name, expr in self.points.items():
            if not isinstance(name, str) or not name:
                raise DrawingError(f"Drawing.points: point names must be non-empty strings, got {name!r}")
            try:
                e = ca.SX(expr)
            except Exception:
                raise DrawingError(f"point {name!r}: {type(expr).__name__} is not a CasADi SX expression "
                                   "(build points from model.q and model.theta)") from None
            if e.numel() != 2:
                raise DrawingError(f"point {name!r} has shape {e.shape}; a point is a 2-vector (x, y) in the plane")
            pts[name] = ca.reshape(e, 2, 1)
        links = []
        for i, link in enumerate(self.links):
            if not isinstance(link, (tuple, list)) or len(link) not in (2, 3):
                raise DrawingError(f"link {i}: expected (a, b) or (a, b, style), got {link!r}")
            for nm in link[:2]:
                if nm not in pts:
                    raise DrawingError(f"link {i} {tuple(link[:2])!r} names unknown point {nm!r}; "
                                       f"known points: {sorted(pts)}")
            links.append((link[0], link[1], _merged(LINK_STYLE, _style(link[2] if len(link) == 3 else None,
                                                                        f"link {i}"))))
        segs = []
        for i, seg in enumerate(self.segments):
            ok = isinstance(seg, (tuple, list)) and len(seg) in (2, 3)
            xy = np.asarray(seg[:2], float) if ok else None
            if not ok or xy.shape != (2, 2) or not np.all(np.isfinite(xy)):
                raise DrawingError(f"segment {i}: expected ((x0, y0), (x1, y1)) or with a style dict, got {seg!r}")
            segs.append((xy, _merged(SEGMENT_STYLE, _style(seg[2] if len(seg) == 3 else None, f"segment {i}"))))
        if self.limits is not None:
            lim = np.asarray(self.limits, float)
            if lim.shape != (2, 2) or not np.all(np.isfinite(lim)) or np.any(lim[:, 1] <= lim[:, 0]):
                raise DrawingError(f"limits must be ((xmin, xmax), (ymin, ymax)) with min < max, got {self.limits!r}")
            object.__setattr__(self, "limits", (tuple(lim[0]), tuple(lim[1])))
        ps = POINT_STYLE if self.point_style is None else _style(self.point_style, "point_style")
        object.__setattr__(self, "points", dict(pts))
        object.__setattr__(self, "links", tuple(links))
        object.__setattr__(self, "segments", tuple(segs))
        object.__setattr__(self, "point_style", dict(ps))
        object.__setattr__(self, "_sx", ca.horzcat(*pts.values()))

    @property
    def names(self) -> list[str]:
        return list(self.points)

    def function(self, model) -> ca.Function:
        """``(q, theta) -> P`` with ``P[:, j]`` the position of point ``j`` (order of :attr:`names`)."""
        allowed = ca.vertcat(model.q, model.theta)
        rest = ca.substitute(self._sx, allowed, ca.DM.zeros(allowed.shape))
        stray = sorted({s.name() for s in ca.symvar(rest)})
        if stray:
            bad = [n for n, e in self.points.items()
                   if ca.symvar(ca.substitute(e, allowed, ca.DM.zeros(allowed.shape)))]
            own = {s.name() for s in ca.symvar(allowed)}
            hint = ("; they have the names of this model's symbols but are other symbols: the drawing was "
                    "made for another Model instance (a second build()); call drawing(model) with the model "
                    "you animate") if set(stray) <= own else "; points may use only model.q and model.theta"
            raise DrawingError(f"points {bad} depend on symbols {stray} that are not q or parameters of "
                               f"model {model.name!r}{hint}")
        return ca.Function("drawing", [model.q, model.theta], [self._sx], ["q", "theta"], ["P"])


# ---------------------------------------------------------------------------
def _theta(model, theta) -> np.ndarray:
    if theta is None:
        return model.theta_values
    if isinstance(theta, Mapping):
        unknown = sorted(set(theta) - set(model.params.names))
        if unknown:
            raise ParameterError(f"unknown parameters {unknown} for model {model.name!r}; known: {model.params.names}")
        return model.with_params(**{k: float(v) for k, v in theta.items()}).theta_values
    th = np.asarray(theta, float).ravel()
    if th.size != len(model.params.names):
        raise DimensionError(f"theta has {th.size} values, model {model.name!r} has {len(model.params.names)} "
                             f"parameters {model.params.names}")
    return th


def _times(t) -> np.ndarray:
    t = np.asarray(t, float)
    if t.ndim != 1 or t.size < 2:
        raise DimensionError(f"t must be a 1-D array of at least 2 times, got shape {t.shape}")
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) < 0) or not t[-1] > t[0]:
        raise AnimationError("t must be finite, non-decreasing and span a positive duration")
    return t


def _history(model, t: np.ndarray, q) -> np.ndarray:
    """``q`` as ``(n, len(t))``.  Every result type stores ``q`` as ``(n, N)`` (time along the last
    axis: ClosedLoopResult, ContactTrajectory, Inverse.q(t)); a raw ``(N, n)`` array (time first) is
    transposed only when that reading is unambiguous (``n != N``): a square array is always read as
    ``(n, N)``."""
    n, N = model.n, t.size
    Q = np.asarray(q, float)
    if Q.ndim == 2 and Q.shape == (n, N):
        pass
    elif Q.ndim == 2 and Q.shape == (N, n):  # n != N here: the square case was taken as time last
        Q = Q.T
    else:
        raise DimensionError(f"q has shape {Q.shape}; for model {model.name!r} (n = {n}) and {N} times it must be "
                             f"({n}, {N}) or ({N}, {n})")
    bad = np.flatnonzero(~np.all(np.isfinite(Q), axis=0))
    if bad.size:
        raise AnimationError(f"q is not finite from t = {t[bad[0]]:g} on (sample {bad[0]}); animate the finite "
                             f"part: t[:{bad[0]}], q[:, :{bad[0]}]")
    return Q


def _sample(model, t: np.ndarray, q, times: np.ndarray) -> np.ndarray:
    """``q`` at ``times`` (linear interpolation of samples, or a callable ``q(times)``)."""
    if callable(q):
        Q = np.asarray(q(times), float)
        if Q.shape != (model.n, times.size):
            raise DimensionError(f"q(t) returned shape {Q.shape}, expected ({model.n}, {times.size})")
        if not np.all(np.isfinite(Q)):
            raise AnimationError("q(t) returned non-finite values")
        return Q
    Q = _history(model, t, q)
    i = np.clip(np.searchsorted(t, times, side="right") - 1, 0, t.size - 2)
    dt = t[i + 1] - t[i]
    w = np.where(dt > 0, (times - t[i]) / np.where(dt > 0, dt, 1.0), 1.0)
    return Q[:, i] * (1 - w) + Q[:, i + 1] * w


def _positions(model, drawing: Drawing, Q: np.ndarray, theta) -> np.ndarray:
    """All points for all columns of ``Q`` by one mapped call: shape ``(N, npoints, 2)``."""
    N, npts = Q.shape[1], len(drawing.points)
    P = np.array(drawing.function(model).map(N)(Q, _theta(model, theta)))
    return P.reshape(2, N, npts).transpose(1, 2, 0)


def positions(model, drawing: Drawing, q, theta=None) -> dict[str, np.ndarray]:
    """Point positions for configurations ``q`` (shape ``(n, N)``): name -> array ``(2, N)``."""
    Q = np.asarray(q, float)
    if Q.ndim == 1:
        Q = Q[:, None]
    if Q.ndim != 2 or Q.shape[0] != model.n:
        raise DimensionError(f"q has shape {np.asarray(q).shape}; model {model.name!r} needs ({model.n}, N)")
    P = _positions(model, drawing, Q, theta)
    return {name: P[:, j, :].T for j, name in enumerate(drawing.names)}


def _limits(drawing: Drawing, P: np.ndarray, margin: float = 0.08):
    if drawing.limits is not None:
        return drawing.limits
    xy = P.reshape(-1, 2)
    if drawing.segments:
        xy = np.vstack([xy] + [s[0] for s in drawing.segments])
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    span = hi - lo
    pad = np.maximum(margin * span, 0.05 * max(span.max(), 1e-3))
    return (lo[0] - pad[0], hi[0] + pad[0]), (lo[1] - pad[1], hi[1] + pad[1])


def _trail_index(drawing: Drawing, trail) -> list[int]:
    if trail is None:
        return []
    names = [trail] if isinstance(trail, str) else list(trail)
    unknown = [n for n in names if n not in drawing.points]
    if unknown:
        raise DrawingError(f"trail names unknown points {unknown}; known points: {drawing.names}")
    return [drawing.names.index(n) for n in names]


def _figure(drawing: Drawing, limits, figsize, dpi, title):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.set(xlim=limits[0], ylim=limits[1], aspect="equal", xlabel=drawing.axis_labels[0],
           ylabel=drawing.axis_labels[1])
    ax.grid(True, lw=0.4, alpha=0.5)
    for xy, style in drawing.segments:
        ax.plot(xy[:, 0], xy[:, 1], **style)
    if title:
        ax.set_title(title)
    return fig, ax


class _Pose:
    """The artists of one pose, updated in place from positions ``(npoints, 2)``."""

    def __init__(self, ax, drawing: Drawing, alpha: float = 1.0):
        idx = {n: j for j, n in enumerate(drawing.names)}
        self.pairs = [(idx[a], idx[b]) for a, b, _ in drawing.links]
        fade = lambda st: {**st, "alpha": alpha * st.get("alpha", 1.0)}  # noqa: E731
        self.lines = [ax.plot([], [], **fade(style))[0] for _, _, style in drawing.links]
        self.points = ax.plot([], [], **fade(drawing.point_style))[0] if drawing.point_style else None
        self.artists = [*self.lines, *([self.points] if self.points is not None else [])]

    def update(self, p: np.ndarray):
        for (a, b), line in zip(self.pairs, self.lines):
            line.set_data(p[[a, b], 0], p[[a, b], 1])
        if self.points is not None:
            self.points.set_data(p[:, 0], p[:, 1])


def _check_format(path: Path) -> None:
    suffix = path.suffix.lower()
    if suffix == ".mp4" and not shutil.which("ffmpeg"):
        raise AnimationError(f"writing {path.name} needs ffmpeg, which is not installed on this machine; "
                             f"write a GIF instead: {path.with_suffix('.gif')}")
    if suffix not in (".gif", ".mp4"):
        raise AnimationError(f"cannot write animation {path.name!r}: use a .gif or .mp4 file name")


def _renderer(fig, ax, artists, update):
    """``render(f)``: frame ``f`` as an RGB image (Pillow).  The static part of the figure (axes,
    fixed segments, title, layout) is drawn once; each frame restores that image and draws only the
    moving ``artists`` after ``update(f)`` (blitting)."""
    from PIL import Image

    canvas = fig.canvas
    for artist in artists:
        artist.set_animated(True)
    canvas.draw()  # skips the animated artists
    background = canvas.copy_from_bbox(fig.bbox)

    def render(f: int):
        update(f)
        canvas.restore_region(background)
        for artist in artists:
            ax.draw_artist(artist)
        return Image.fromarray(np.asarray(canvas.buffer_rgba())).convert("RGB")

    return render


def _clock(fig, ax):
    """``stamp(image, text)``: ``text`` in the upper left corner of the axes, black monospace on a white
    box, drawn by Pillow (a matplotlib text artist is laid out anew for every new string: ~3 ms, most of
    a frame's time)."""
    from matplotlib import font_manager, rcParams
    from PIL import ImageDraw, ImageFont

    size = rcParams["font.size"] * fig.dpi / 72
    try:
        font = ImageFont.truetype(font_manager.findfont("monospace"), size=max(1, round(size)))
    except (OSError, ImportError):  # a Pillow without FreeType
        font = ImageFont.load_default()
    x, y = ax.transAxes.transform((0.02, 0.96))
    y = fig.bbox.height - y
    pad = max(1, round(size / 10))

    def stamp(image, text: str):
        draw = ImageDraw.Draw(image, "RGBA")
        x0, y0, x1, y1 = draw.textbbox((x, y), text, font=font)
        draw.rectangle((x0 - pad, y0 - pad, x1 + pad, y1 + pad), fill=(255, 255, 255, 204))
        draw.text((x, y), text, font=font, fill=(0, 0, 0, 255))
        return image

    return stamp


def _write_gif(path: Path, render, n_frames: int, fps: float) -> None:
    """GIF with one palette for all frames, made once from the first and last frames (which show every
    artist and the whole trails); each frame is mapped to it without dithering."""
    from PIL import Image

    ends = np.vstack([np.asarray(render(0)), np.asarray(render(n_frames - 1))])
    palette = Image.fromarray(ends).quantize(colors=255, method=Image.Quantize.MEDIANCUT)
    images = [render(f).quantize(palette=palette, dither=Image.Dither.NONE) for f in range(n_frames)]
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(round(1000 / fps)), loop=0,
                   optimize=False)


def _write_mp4(path: Path, frames, fps: float) -> None:
    """MP4 (H.264) by piping raw RGB frames to ffmpeg; an incomplete file is removed."""
    import subprocess

    ffmpeg = shutil.which("ffmpeg") or "ffmpeg"  # checked by the caller
    proc: subprocess.Popen | None = None
    try:
        for rgb in frames:
            if proc is None:
                w, h = rgb.size
                proc = subprocess.Popen([ffmpeg, "-y", "-loglevel", "error", "-f", "rawvideo",
                                         "-pix_fmt", "rgb24", "-s", f"{w}x{h}", "-r", f"{fps:g}", "-i", "-",
                                         "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2", "-vcodec", "h264",
                                         "-pix_fmt", "yuv420p", str(path)],
                                        stdin=subprocess.PIPE, stderr=subprocess.PIPE)
            assert proc.stdin is not None  # stdin=PIPE
            try:
                proc.stdin.write(rgb.tobytes())
            except BrokenPipeError:  # ffmpeg stopped reading: its message says why
                break
        if proc is None:
            raise AnimationError(f"no frames to write to {path}: the run has no samples")
        assert proc.stdin is not None and proc.stderr is not None  # both PIPE
        try:
            proc.stdin.close()
        except BrokenPipeError:
            pass
        err = proc.stderr.read().decode(errors="replace").strip()
        if proc.wait() != 0:
            raise AnimationError(f"ffmpeg could not write {path}: {err or 'exit code ' + str(proc.returncode)}; "
                                 f"write a GIF instead: {path.with_suffix('.gif')}")
    except BaseException:
        if proc is not None:
            proc.kill()
            proc.wait()
        path.unlink(missing_ok=True)
        raise


def animate(model, drawing: Drawing, t, q, path, *, fps: float = 25, speed: float = 1.0, trail=None,
            title: str | None = None, theta=None, figsize=(6.0, 4.5), dpi: int = 80,
            max_frames: int = 3000) -> Path:
    """Write an animation of the motion ``q(t)`` to ``path`` (``.gif`` or ``.mp4``).

    Parameters
    ----------
    model : Model
        The model whose ``q`` and ``theta`` the drawing uses.
    drawing : Drawing
        Points and links (a scene's ``drawing(model)``).
    t : array_like (N,)
        Times of the samples (non-decreasing; repeated times at events are fine).
    q : array_like (n, N), or callable
        Configurations at ``t``, time along the last axis (``ClosedLoopResult.q`` or
        ``ContactTrajectory.q``), or a function ``times -> (n, len(times))`` such as ``Inverse.q``.
        A time-first ``(N, n)`` array is accepted when ``n != N`` (unambiguous); a square array
        is read as ``(n, N)``.
    path : str or Path
        Output file; ``.gif`` (Pillow) or ``.mp4`` (needs ffmpeg).
    fps : float
        Frames per second of the video.  GIF delays are whole hundredths of a second:
        10, 20, 25 or 50 fps play at exactly ``speed``.
    speed : float
        Seconds of motion per second of video (0.5 = slow motion).
    trail : str or sequence of str, optional
        Points whose path so far is drawn.
    title : str, optional
        Axes title; the time is shown in every frame.
    theta : dict or array_like, optional
        Parameter values (overrides by name, or the full vector); default the model's.
    figsize, dpi :
        Frame size in inches and dots per inch: frames are ``figsize * dpi`` pixels.
    max_frames : int
        Refuse longer animations (raise ``speed`` or lower ``fps``).

    Returns
    -------
    Path
        ``path``.  Frames are at ``n = round(duration fps / speed) + 1`` uniform times
        from ``t[0]`` to ``t[-1]`` (samples interpolated linearly); axis limits are fixed
        from the whole motion.
    """
    path = Path(path)
    if not (np.isfinite(fps) and fps > 0 and np.isfinite(speed) and speed > 0):
        raise AnimationError(f"fps and speed must be positive, got fps={fps}, speed={speed}")
    _check_format(path)
    t = _times(t)
    n_frames = max(2, int(round((t[-1] - t[0]) * fps / speed)) + 1)
    if n_frames > max_frames:
        raise AnimationError(f"{n_frames} frames for {t[-1] - t[0]:g} s at fps={fps}, speed={speed} exceed "
                             f"max_frames={max_frames}: raise speed, lower fps or raise max_frames")
    times = np.linspace(t[0], t[-1], n_frames)
    P = _positions(model, drawing, _sample(model, t, q, times), theta)
    trails = _trail_index(drawing, trail)
    fig, ax = _figure(drawing, _limits(drawing, P), figsize, dpi, title)
    pose = _Pose(ax, drawing)
    paths = [ax.plot([], [], **TRAIL_STYLE)[0] for _ in trails]

    def update(f):
        pose.update(P[f])
        for j, line in zip(trails, paths):
            line.set_data(P[:f + 1, j, 0], P[:f + 1, j, 1])

    path.parent.mkdir(parents=True, exist_ok=True)
    render = _renderer(fig, ax, [*pose.artists, *paths], update)
    stamp = _clock(fig, ax)  # after the layout: the axes are where they stay

    def frame(f):
        return stamp(render(f), f"t = {times[f]:7.3f} s")

    if path.suffix.lower() == ".mp4":
        _write_mp4(path, map(frame, range(n_frames)), fps)
    else:
        _write_gif(path, frame, n_frames, fps)
    return path


def snapshot(model, drawing: Drawing, t, q, path, *, times=None, n: int = 5, trail=None, title: str | None = None,
             theta=None, figsize=(6.0, 4.5), dpi: int = 120) -> Path:
    """Draw a few poses of the motion in one image (PNG, PDF, SVG by the suffix of ``path``).

    Poses are at ``times`` (default ``n`` uniform times from ``t[0]`` to ``t[-1]``), fading
    from light (early) to opaque (late); ``trail`` points show their whole path.
    Other arguments as in :func:`animate`.
    """
    path = Path(path)
    t = _times(t)
    times = np.linspace(t[0], t[-1], int(n)) if times is None else np.atleast_1d(np.asarray(times, float))
    if times.ndim != 1 or times.size < 1 or np.any(times < t[0]) or np.any(times > t[-1]):
        raise AnimationError(f"snapshot times must lie in [{t[0]:g}, {t[-1]:g}], got {np.asarray(times).tolist()}")
    trails = _trail_index(drawing, trail)
    dense = np.linspace(t[0], t[-1], 400) if trails else times
    P_all = _positions(model, drawing, _sample(model, t, q, np.unique(np.r_[times, dense])), theta)
    P = _positions(model, drawing, _sample(model, t, q, times), theta)
    label = ", ".join(f"{x:g}" for x in times)
    fig, ax = _figure(drawing, _limits(drawing, P_all), figsize, dpi, (title + "\n" if title else "") +
                      f"poses at t = {label} s")
    for j in trails:
        ax.plot(P_all[:, j, 0], P_all[:, j, 1], **TRAIL_STYLE)
    for f in range(times.size):
        _Pose(ax, drawing, alpha=0.25 + 0.75 * (f + 1) / times.size).update(P[f])
    path.parent.mkdir(parents=True, exist_ok=True)
    from . import save

    save(fig, path)
    return path


def animate_result(result, path, *, scene=None, params=None, fps: float = 25, speed: float = 1.0,
                   title: str | None = None, **options) -> Path:
    """Draw a run of a scene (``ClosedLoopResult``, ``ContactTrajectory`` or ``Inverse``) to ``path``.

    The scene and its parameters default to what the result records (``result.meta``, filled by the
    commands and kept in its file); the scene's ``drawing(model)`` says what to draw.  A recorded
    scene file is never loaded (loading runs its code): pass it as ``scene=`` if you trust it.
    """
    meta = dict(getattr(result, "meta", None) or {})
    if scene is None:
        scene = meta.get("scene")
        if isinstance(scene, str) and _is_path(scene):
            raise SceneError(f"the result was computed with the scene file {scene!r}; a scene file is code and is "
                             "not loaded because a result names it: pass scene= (that path, if you trust it)")
    if scene is None:
        raise AnimationError("the result does not record its scene: pass scene= (a Scene, name or path)")
    scene = scene if isinstance(scene, Scene) else load_scene(scene)
    if scene.drawing is None:
        raise AnimationError(f"scene {scene.name!r} declares no drawing(model) (points and links to draw)")
    model = scene.model(meta.get("params", {}) if params is None else params)
    label = getattr(result, "controller", "") or meta.get("controller", "")
    return animate(model, scene.drawing(model), *frames(result, model), path, fps=fps, speed=speed,
                   title=title or (scene.name + (f" ({label})" if label else "")), **options)


def frames(result, model) -> tuple[np.ndarray, np.ndarray]:
    """``(t, q)`` to draw of a run (an inverse: its state trajectory over the horizon)."""
    if hasattr(result, "X_mesh"):
        t = np.linspace(result.T0, result.Tf, 600)
        return t, result.q(t)
    t, q = np.asarray(result.t, float), np.asarray(result.q, float)  # time along the last axis: (n, len(t))
    if q.shape != (model.n, t.size):
        raise DimensionError(f"{type(result).__name__}.q has shape {q.shape}; for model {model.name!r} "
                             f"(n = {model.n}) and {t.size} times it must be ({model.n}, {t.size}) "
                             "(time along the last axis)")
    return t, q
