"""Drawings and animations of planar mechanisms (invctl.plot.animate).

Point positions are checked against closed-form kinematics (cart-pole) and against the
loop closure of the manipulator (both sides of the closed loop meet where g(q) = 0, and the
tip is the printed end-effector map r_app of 003 Sect. 6 at gamma = 0); files are read back.
"""
import math
import shutil

import casadi as ca
import matplotlib.pyplot as plt
import numpy as np
import pytest
from PIL import Image

from invctl.errors import AnimationError, DimensionError, DrawingError, ParameterError
from invctl.plot.animate import Drawing, _sample, animate, positions, snapshot


@pytest.fixture(scope="module")
def cartpole():
    import invctl_scenes.cartpole as scene

    return scene.build()


def cartpole_drawing(model):
    x, th = model.q[0], model.q[1]
    l = model.params["l"]
    return Drawing(
        points={"cart": ca.vertcat(x, 0), "com": ca.vertcat(x + l * ca.sin(th), l * ca.cos(th)),
                "tip": ca.vertcat(x + 2 * l * ca.sin(th), 2 * l * ca.cos(th)),
                "left": ca.vertcat(x - 0.15, 0), "right": ca.vertcat(x + 0.15, 0)},
        links=[("left", "right", {"lw": 8, "color": "k"}), ("cart", "tip")],
        segments=[((-2.0, -0.05), (2.0, -0.05))],
    )


def manipulator_drawing(model):
    """Rails of both actuators, body 1 (s1 -> joint A), body 2 (A -> B, centre at d + s2 on the
    second rail), body 3 (B -> tip)."""
    s1, s2, al, be, ga = (model.q[i] for i in range(5))
    P = model.params
    L1, L2, L3, d = P["L1"], P["L2"], P["L3"], P["d"]
    B = ca.vertcat(d + s2 + 0.5 * L2 * ca.cos(be), -0.5 * L2 * ca.sin(be))
    return Drawing(
        points={"base1": ca.vertcat(0, s1), "A": ca.vertcat(L1 * ca.cos(al), s1 + L1 * ca.sin(al)),
                "A2": ca.vertcat(d + s2 - 0.5 * L2 * ca.cos(be), 0.5 * L2 * ca.sin(be)),
                "centre2": ca.vertcat(d + s2, 0), "B": B,
                "tip": B + L3 * ca.vertcat(ca.cos(be + ga), -ca.sin(be + ga))},
        links=[("base1", "A"), ("A2", "B", {"color": "tab:orange"}), ("B", "tip", {"color": "tab:green"})],
        segments=[((0.0, -1.0), (0.0, 1.0)), ((0.0, 0.0), (2.5, 0.0))],
    )


def motion(t):
    return np.vstack([0.5 * np.sin(t), 0.3 * np.sin(3 * t)])


def test_cartpole_points_closed_form(cartpole):
    rng = np.random.default_rng(0)
    q = np.vstack([rng.uniform(-1, 1, 50), rng.uniform(-1.5, 1.5, 50)])
    for theta, l in ((None, cartpole.values["l"]), ({"l": 0.8}, 0.8)):
        pos = positions(cartpole, cartpole_drawing(cartpole), q, theta=theta)
        x, th = q
        # same trigonometry in numpy and in the compiled CasADi map: equal to rounding
        assert np.allclose(pos["cart"], np.vstack([x, 0 * x]), atol=1e-15)
        assert np.allclose(pos["com"], np.vstack([x + l * np.sin(th), l * np.cos(th)]), atol=1e-14)
        assert np.allclose(pos["tip"], np.vstack([x + 2 * l * np.sin(th), 2 * l * np.cos(th)]), atol=1e-14)
        assert np.allclose(np.hypot(*(pos["tip"] - pos["cart"])), 2 * l, atol=1e-14)


def test_manipulator_drawing_closes_the_loop(manipulator):
    import invctl_scenes.manipulator as scene

    dr = manipulator_drawing(manipulator)
    q0 = scene.initial_configuration(manipulator)
    assert np.max(np.abs(manipulator.evaluate("g", q0))) < 1e-12
    # a few more configurations on the loop: vary s2, beta, gamma and solve g = 0 for (s1, alpha)
    p = manipulator.values
    qs = [q0]
    for s2, be, ga in ((0.1, 0.5, 0.2), (-0.2, 0.8, -0.4)):
        ca_ = (s2 + p["d"] - 0.5 * p["L2"] * math.cos(be)) / p["L1"]
        al = math.acos(ca_)
        s1 = 0.5 * p["L2"] * math.sin(be) - p["L1"] * math.sin(al)
        qs.append(np.array([s1, s2, al, be, ga]))
    Q = np.array(qs).T
    assert np.max(np.abs(manipulator.evaluate("g", Q[:, 1]))) < 1e-12
    pos = positions(manipulator, dr, Q)
    # joint A from body 1 and from body 2 coincide exactly where g(q) = 0 (the loop closure (49))
    assert np.allclose(pos["A"], pos["A2"], atol=1e-14)
    # at gamma = 0 the tip is r_app(y) of 003 Sect. 6; in general it is at L3 from B
    y = np.array([manipulator.evaluate("h", Q[:, j], np.zeros(5)).ravel() for j in range(Q.shape[1])]).T
    r_app = scene.end_effector_approx(manipulator, y)
    assert np.allclose(pos["tip"][:, 0], r_app[:, 0], atol=1e-14)
    assert np.allclose(np.hypot(*(pos["tip"] - pos["B"])), p["L3"], atol=1e-14)


def test_gif_frames_size_and_orientation(cartpole, tmp_path):
    t = np.linspace(0.0, 2.0, 81)
    q = motion(t)
    figs_before = plt.get_fignums()
    path = animate(cartpole, cartpole_drawing(cartpole), t, q, tmp_path / "sub" / "cp.gif", fps=10,
                   trail="tip", title="cart-pole", figsize=(4, 3), dpi=50)
    with Image.open(path) as im:
        # n = round(duration fps / speed) + 1 = 21 frames of figsize x dpi = 200 x 150 pixels, 100 ms each
        assert (im.n_frames, im.size, im.info["duration"]) == (21, (200, 150), 100)
        frames = []
        for k in (0, 20):
            im.seek(k)
            frames.append(np.asarray(im.convert("RGB"), float))
    assert np.abs(frames[0] - frames[1]).sum() > 0  # it moves
    fast = animate(cartpole, cartpole_drawing(cartpole), t, q, tmp_path / "fast.gif", fps=10, speed=2.0,
                   figsize=(4, 3), dpi=50)
    with Image.open(fast) as im:
        assert im.n_frames == 11
    # a raw array with time along the first axis (unambiguous: n = 2 != 81 samples) gives the same file
    again = animate(cartpole, cartpole_drawing(cartpole), t, q.T, tmp_path / "t.gif", fps=10, trail="tip",
                    title="cart-pole", figsize=(4, 3), dpi=50)
    assert again.read_bytes() == path.read_bytes()
    assert plt.get_fignums() == figs_before  # nothing left open in pyplot


def test_callable_q_and_interpolation(cartpole, tmp_path):
    t = np.linspace(0.0, 1.0, 11)
    q = motion(t)
    times = np.array([0.0, 0.05, 0.5, 0.97, 1.0])
    lin = _sample(cartpole, t, q, times)
    expected = np.vstack([np.interp(times, t, q[i]) for i in range(2)])
    assert np.allclose(lin, expected, atol=1e-15)
    # repeated times (an impact event recorded twice) are accepted
    t2 = np.r_[t[:5], t[4], t[5:]]
    q2 = np.c_[q[:, :5], q[:, 4], q[:, 5:]]
    assert np.allclose(_sample(cartpole, t2, q2, times), expected, atol=1e-15)
    path = animate(cartpole, cartpole_drawing(cartpole), [0.0, 1.0], motion, tmp_path / "f.gif", fps=20,
                   figsize=(3, 2), dpi=40)
    with Image.open(path) as im:
        assert (im.n_frames, im.size) == (21, (120, 80))


def test_square_history_is_read_time_last(cartpole):
    """Every result stores q as (n, N); a square q (n == N) is never transposed: it is (n, N)."""
    t = np.array([0.0, 1.0])
    q = np.array([[0.1, 0.2], [0.3, 0.4]])  # q1 = (0.1, 0.2), q2 = (0.3, 0.4) over the two times
    np.testing.assert_array_equal(_sample(cartpole, t, q, t), q)
    np.testing.assert_allclose(_sample(cartpole, t, q, np.array([0.5])), [[0.15], [0.35]], atol=1e-15)


def test_snapshot_png(cartpole, tmp_path):
    t = np.linspace(0.0, 2.0, 41)
    path = snapshot(cartpole, cartpole_drawing(cartpole), t, motion(t), tmp_path / "poses.png", n=4,
                    trail="tip", figsize=(5, 4), dpi=60)
    with Image.open(path) as im:
        assert im.size == (300, 240)
    with pytest.raises(AnimationError, match="must lie in"):
        snapshot(cartpole, cartpole_drawing(cartpole), t, motion(t), tmp_path / "x.png", times=[3.0])


def test_bad_drawings(cartpole):
    x, th = cartpole.q[0], cartpole.q[1]
    with pytest.raises(DrawingError, match="unknown point 'tipp'"):
        Drawing({"cart": ca.vertcat(x, 0), "tip": ca.vertcat(x + ca.sin(th), ca.cos(th))}, links=[("cart", "tipp")])
    with pytest.raises(DrawingError, match="2-vector"):
        Drawing({"p": ca.vertcat(x, 0, 1)})
    with pytest.raises(DrawingError, match="style"):
        Drawing({"a": ca.vertcat(x, 0), "b": ca.vertcat(0, 0)}, links=[("a", "b", "red")])
    with pytest.raises(DrawingError, match="limits"):
        Drawing({"a": ca.vertcat(x, 0)}, limits=((1, 0), (0, 1)))
    with pytest.raises(DrawingError, match="non-empty"):
        Drawing({})
    # symbols that are not q or parameters
    u = ca.SX.sym("u")
    bad = Drawing({"a": ca.vertcat(x + u, 0), "b": ca.vertcat(x, 0)})
    with pytest.raises(DrawingError, match=r"\['a'\] depend on symbols \['u'\]"):
        positions(cartpole, bad, np.zeros((2, 3)))
    # a drawing made for another instance of the same scene: same names, other symbols
    import invctl_scenes.cartpole as scene

    other = scene.build()
    with pytest.raises(DrawingError, match="another Model instance"):
        positions(cartpole, cartpole_drawing(other), np.zeros((2, 3)))


def test_bad_inputs(cartpole, tmp_path):
    dr = cartpole_drawing(cartpole)
    t = np.linspace(0, 1, 11)
    with pytest.raises(DimensionError, match=r"q has shape \(3, 11\).*\(2, 11\) or \(11, 2\)"):
        animate(cartpole, dr, t, np.zeros((3, 11)), tmp_path / "a.gif")
    with pytest.raises(DimensionError, match="needs \\(2, N\\)"):
        positions(cartpole, dr, np.zeros((3, 4)))
    q = motion(t)
    q[1, 6:] = np.nan
    with pytest.raises(AnimationError, match=r"not finite from t = 0.6.*t\[:6\]"):
        animate(cartpole, dr, t, q, tmp_path / "a.gif")
    with pytest.raises(AnimationError, match="non-decreasing"):
        animate(cartpole, dr, t[::-1], motion(t), tmp_path / "a.gif")
    with pytest.raises(AnimationError, match=r"use a \.gif or \.mp4"):
        animate(cartpole, dr, t, motion(t), tmp_path / "a.avi")
    with pytest.raises(AnimationError, match="max_frames"):
        animate(cartpole, dr, np.linspace(0, 1000, 11), motion(t), tmp_path / "a.gif")
    with pytest.raises(DrawingError, match="trail names unknown points"):
        animate(cartpole, dr, t, motion(t), tmp_path / "a.gif", trail="nose")
    with pytest.raises(ParameterError, match="unknown parameters \\['length'\\]"):
        animate(cartpole, dr, t, motion(t), tmp_path / "a.gif", theta={"length": 1.0})
    if shutil.which("ffmpeg") is None:
        with pytest.raises(AnimationError, match=r"needs ffmpeg.*a\.gif"):
            animate(cartpole, dr, t, motion(t), tmp_path / "a.mp4")
    else:
        assert animate(cartpole, dr, t, motion(t), tmp_path / "a.mp4", fps=10, dpi=40).stat().st_size > 0


def test_gif_draws_the_figure_once_and_quantizes_one_palette(cartpole, tmp_path, monkeypatch):
    # frames are blitted (the static figure is drawn once, each frame redraws only the moving artists) and
    # every frame is mapped to one palette computed once per animation (not one adaptive palette per frame)
    from matplotlib.figure import Figure

    counts = {"draw": 0, "palette": 0, "mapped": 0}
    draw, quantize, convert = Figure.draw, Image.Image.quantize, Image.Image.convert

    def counted_draw(self, renderer):
        counts["draw"] += 1
        return draw(self, renderer)

    def counted_quantize(self, *args, palette=None, **kwargs):
        counts["palette" if palette is None else "mapped"] += 1
        return quantize(self, *args, palette=palette, **kwargs)

    def counted_convert(self, mode=None, *args, **kwargs):
        counts["palette"] += mode == "P" and self.mode != "P" and kwargs.get("palette") == Image.Palette.ADAPTIVE
        return convert(self, mode, *args, **kwargs)

    monkeypatch.setattr(Figure, "draw", counted_draw)
    monkeypatch.setattr(Image.Image, "quantize", counted_quantize)
    monkeypatch.setattr(Image.Image, "convert", counted_convert)
    t = np.linspace(0.0, 2.0, 81)
    path = animate(cartpole, cartpole_drawing(cartpole), t, motion(t), tmp_path / "cp.gif", fps=10, trail="tip",
                   figsize=(4, 3), dpi=50)
    assert counts == {"draw": 1, "palette": 1, "mapped": 21}
    with Image.open(path) as im:
        assert im.n_frames == 21 and im.mode == "P"
        first = im.getpalette()
        im.seek(20)
        last = np.asarray(im.convert("RGB"))
    assert first is not None and len(first) >= 3 * 8
    # the trail's color is in the palette: the last frame shows the trail in its own color
    trail_rgb = np.array([int(plt.matplotlib.colors.to_hex("C0")[i:i + 2], 16) for i in (1, 3, 5)])
    assert (np.abs(last.astype(int) - trail_rgb).sum(axis=2) < 30).sum() > 10


def test_mp4_pipes_raw_frames_to_ffmpeg(cartpole, tmp_path, monkeypatch):
    # a stand-in ffmpeg that stores what it is given: 21 raw RGB frames of 200 x 150 pixels
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    fake = bin_dir / "ffmpeg"
    fake.write_text('#!/bin/sh\nfor a; do last="$a"; done\necho "$@" > "$last.args"\ncat > "$last"\n')
    fake.chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}:/usr/bin:/bin")
    t = np.linspace(0.0, 2.0, 81)
    path = animate(cartpole, cartpole_drawing(cartpole), t, motion(t), tmp_path / "cp.mp4", fps=10,
                   figsize=(4, 3), dpi=50)
    assert path.stat().st_size == 21 * 200 * 150 * 3
    args = (tmp_path / "cp.mp4.args").read_text().split()
    assert args[args.index("-s") + 1] == "200x150" and args[args.index("-r") + 1] == "10"
    # a failing ffmpeg: a specific error naming the GIF alternative, and no partial file left behind
    # (one that reads all frames first, one that stops reading at once)
    for script in ('cat > /dev/null\necho "Unknown encoder" >&2\nexit 1', 'echo "Unknown encoder" >&2\nexit 1'):
        fake.write_text(f"#!/bin/sh\n{script}\n")
        with pytest.raises(AnimationError, match=r"ffmpeg could not write .*Unknown encoder.*bad\.gif"):
            animate(cartpole, cartpole_drawing(cartpole), t, motion(t), tmp_path / "bad.mp4", fps=10,
                    figsize=(4, 3), dpi=50)
        assert not (tmp_path / "bad.mp4").exists()


def test_clock_is_stamped_at_the_upper_left_of_the_axes(cartpole):
    from invctl.plot.animate import _clock, _figure

    fig, ax = _figure(cartpole_drawing(cartpole), ((-1, 1), (-1, 1)), (6.0, 4.5), 80, "title")
    fig.canvas.draw()
    stamp = _clock(fig, ax)
    images = [np.asarray(stamp(Image.new("RGB", (480, 360), "white"), f"t = {x:7.3f} s")) for x in (0.0, 1.25)]
    dark = np.argwhere(images[0].sum(axis=2) < 200)
    x0, y1 = ax.transAxes.transform((0.0, 1.0))
    assert dark.size and np.all(dark[:, 1] > x0) and np.all(dark[:, 1] < x0 + 0.5 * ax.bbox.width)
    assert np.all(dark[:, 0] > 360 - y1) and np.all(dark[:, 0] < 360 - y1 + 30)  # within 30 px of the top
    assert np.abs(images[0].astype(int) - images[1]).sum() > 0  # the digits change
