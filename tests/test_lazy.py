"""Scenes model only what they need: derivations happen on first use and are cached.

A contact-only scene never derives a relative degree (the analysis layer is
not even imported), and the analysis of the manipulator derives its Lie
derivatives once per model, whatever is asked afterwards.
"""
import json
import subprocess
import sys
import textwrap

import pytest

from invctl.scenes import load_scene

CONTACT_SCENES = ["bouncing_ball", "prismatic_clearance", "gear_backlash", "stiff_wall", "compliant_wrist"]


@pytest.fixture
def lie_counter(monkeypatch):
    """Counts every Lie derivative L_F, L_K taken by invctl.analysis and every auxiliary-system build."""
    from invctl.analysis import auxiliary

    counts = {"lie": 0, "aux": 0}
    lie_F, lie_K, cached = auxiliary.AuxiliarySystem.lie_F, auxiliary.AuxiliarySystem.lie_K, auxiliary.cached

    def count_F(self, expr):
        counts["lie"] += 1
        return lie_F(self, expr)

    def count_K(self, expr):
        counts["lie"] += 1
        return lie_K(self, expr)

    def count_cached(model, key, build):
        def counted():
            counts["aux"] += key == "aux"
            return build()
        return cached(model, key, counted)

    monkeypatch.setattr(auxiliary.AuxiliarySystem, "lie_F", count_F)
    monkeypatch.setattr(auxiliary.AuxiliarySystem, "lie_K", count_K)
    monkeypatch.setattr(auxiliary, "cached", count_cached)
    return counts


@pytest.mark.timeout(120)
def test_contact_scenes_never_import_the_analysis():
    code = textwrap.dedent(f"""
        import contextlib, io, json, sys
        from invctl.cli import main
        out = {{}}
        for scene in {CONTACT_SCENES!r}:
            with contextlib.redirect_stdout(io.StringIO()):
                rc = main(["simulate", scene, "--t-end", "0.2"])
            out[scene] = [rc, sorted(m for m in sys.modules if m.startswith(("invctl.analysis",
                          "invctl.inversion", "invctl.control.funnel")))]
        print(json.dumps(out))
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=110,
                          env={"MPLBACKEND": "Agg", "PATH": "/usr/bin:/bin"})
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    for scene in CONTACT_SCENES:
        rc, loaded = out[scene]
        assert rc == 0
        assert loaded == [], f"{scene} imported {loaded}"


def test_contact_simulation_takes_no_lie_derivative(lie_counter, capsys):
    from invctl.cli import main

    assert main(["simulate", "bouncing_ball", "--t-end", "0.5", "--json"]) == 0
    assert main(["simulate", "prismatic_clearance", "--t-end", "0.1"]) == 0
    assert lie_counter == {"lie": 0, "aux": 0}
    # and building a model with constraints and an output derives nothing either
    load_scene("manipulator").build()
    assert lie_counter == {"lie": 0, "aux": 0}


def test_analysis_derivations_are_cached_on_first_use(lie_counter):
    from invctl.analysis import internal_dynamics, relative_degree

    model = load_scene("manipulator").build()
    assert lie_counter["lie"] == 0
    rd = relative_degree(model, samples=20)
    first = dict(lie_counter)
    assert first["lie"] > 0 and first["aux"] == 1
    assert rd.r_hat == 2 and rd.r_bar == 8
    # other samples, another seed, a plant with other parameter values: no new derivation
    relative_degree(model, samples=40, rng=3)
    plant = model.scaled(m3=1.2)
    rd_plant = relative_degree(plant, samples=20)
    assert lie_counter == first
    assert rd_plant.worst_condition != rd.worst_condition  # numbers are recomputed, symbols are not
    assert relative_degree(model, samples=20) is rd
    internal_dynamics(model)
    after_internal = dict(lie_counter)
    internal_dynamics(model)
    assert lie_counter == after_internal
    # a new model (new symbols) derives again, once
    other = load_scene("manipulator").build(m3=2.0)
    relative_degree(other, samples=20)
    assert lie_counter["aux"] == first["aux"] + 1


@pytest.mark.timeout(60)
def test_loading_every_scene_imports_no_command_implementation():
    # a scene declares data and model-building functions: the analysis/inversion/studies modules are
    # imported when a command runs, not when a scene is loaded
    code = textwrap.dedent("""
        import json, sys
        from invctl.scenes import available_scenes, load_scene
        names = available_scenes()
        for name in names:
            load_scene(name)
        print(json.dumps([names, sorted(m for m in sys.modules if m.startswith(("invctl.analysis.",
              "invctl.inversion.", "invctl.studies.", "invctl.simulate.", "invctl.control.")))]))
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=50,
                          env={"MPLBACKEND": "Agg", "PATH": "/usr/bin:/bin"})
    assert proc.returncode == 0, proc.stderr
    names, loaded = json.loads(proc.stdout.strip().splitlines()[-1])
    assert len(names) >= 10 and loaded == [], loaded


def test_commands_offered_follow_from_the_declaration():
    assert load_scene("manipulator").commands == ("analyze", "invert", "design", "simulate", "pipeline", "study")
    assert load_scene("knife_edge").commands == ("analyze", "study")
    assert "analyze" in load_scene("gear_backlash").commands  # it declares an analyze report
    assert "analyze" not in load_scene("bouncing_ball").commands
    assert load_scene("stiff_wall").commands == ("analyze", "simulate", "design", "pipeline", "study")


#: heavy modules that neither ``import invctl`` nor loading a shipped scene may import (a command imports
#: what it uses when it runs)
HEAVY_MODULES = ("scipy", "scipy.interpolate", "scipy.linalg", "scipy.optimize", "scipy.special", "scipy.sparse",
                 "matplotlib", "matplotlib.pyplot", "control", "PIL")


@pytest.mark.timeout(60)
def test_importing_invctl_and_the_scenes_imports_no_heavy_module():
    code = textwrap.dedent("""
        import json, sys
        import invctl, invctl.reference, invctl_scenes.manipulator
        first = [m for m in HEAVY if m in sys.modules]
        from invctl.scenes import available_scenes, load_scene
        for name in available_scenes():
            load_scene(name)
        print(json.dumps([first, [m for m in HEAVY if m in sys.modules]]))
    """).replace("HEAVY", repr(HEAVY_MODULES))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=50,
                          env={"MPLBACKEND": "Agg", "PATH": "/usr/bin:/bin"})
    assert proc.returncode == 0, proc.stderr
    first, after_all = json.loads(proc.stdout.strip().splitlines()[-1])
    assert first == [] and after_all == [], (first, after_all)


def test_lazy_reference_attribute_is_the_public_function():
    import invctl.reference as ref
    from invctl.reference.samples import from_samples

    assert ref.from_samples is from_samples and "from_samples" in ref.__all__
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        ref.nope  # noqa: B018
