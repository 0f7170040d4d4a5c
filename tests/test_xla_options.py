"""`KernelOptions.xla`: XLA compiler-option presets (`jaxrt.xla`). Validated like every
setting; the options reach XLA's compile call for every program that renders; images
agree with XLA's defaults to rounding; the preset is part of the jit cache key; flags
that this XLA does not know are dropped with a warning, never an error."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as jr
from jaxrt import xla
from jaxrt.cli import _Failure, main, parse_overrides
from jaxrt.render import compile_render

S = jr.sdf
FAST_CPU = {"xla_backend_optimization_level": 1, "xla_cpu_use_fusion_emitters": False}


def _known(flag, value):
    """Whether this XLA takes `flag` (probed here, not by jaxrt.xla): jax 0.11's XLA:CPU
    has no legacy emitter, so no `xla_cpu_use_fusion_emitters`."""
    try:
        jax.jit(lambda x: x + 1).lower(jnp.float32(0)).compile(compiler_options={flag: value})
    except Exception:  # noqa: BLE001  (XlaRuntimeError: "No such compile option")
        return False
    return True


#: What "fast-compile" passes to XLA here: its CPU flags that this XLA knows on a CPU,
#: nothing on a GPU.
FAST = ({k: v for k, v in FAST_CPU.items() if _known(k, v)}
        if jax.default_backend() == "cpu" else {})


def _scene(radius=0.5):
    """A sphere on a plane, one point light: no creases, so no pixel decided by rounding."""
    return jr.Scene(
        surface=S.Union(S.Translate(S.Sphere(radius=radius, material=0), offset=(0.0, 0.5, 0.0)),
                        S.Plane(normal=(0.0, 1.0, 0.0), offset=0.0, material=1)),
        materials=[jr.bsdf.Lambert(albedo=(0.8, 0.3, 0.2)), jr.bsdf.Lambert(albedo=(0.7, 0.7, 0.7))],
        lights=[jr.PointLight(position=(2.0, 4.0, -3.0), intensity=(30.0, 30.0, 30.0))],
        background=(0.05, 0.05, 0.08))


CAMERA = jr.PerspectiveCamera(eye=(0.0, 1.0, -3.0), target=(0.0, 0.4, 0.0), up=(0.0, 1.0, 0.0),
                              fov=40.0, width=8, height=6)


def _settings(backend, preset):
    return jr.RenderSettings(backend=backend, aovs=(), max_steps=64, shadow_steps=32,
                             kernel=jr.KernelOptions(xla=preset))


@pytest.fixture
def compiles(monkeypatch):
    """[(module name, {option: value})] of every XLA compile while the test runs (a spy
    on JAX's compile call; `jax._src` is internal: the test fails loudly if it moves)."""
    from jax._src import compiler

    seen, original = [], compiler.compile_or_get_cached

    def spy(*args, **kwargs):
        values = list(args) + list(kwargs.values())
        [module] = [v for v in values if hasattr(v, "operation")]
        [options] = [v for v in values if hasattr(v, "env_option_overrides")]
        name = str(module.operation.attributes["sym_name"]).strip('"')
        seen.append((name, dict(options.env_option_overrides)))
        return original(*args, **kwargs)

    monkeypatch.setattr(compiler, "compile_or_get_cached", spy)
    return seen


#: XLA's own values of the flags that the suite's conftest sets in $XLA_FLAGS: the images
#: of "default" below are compiled with them, so that the comparison is with XLA's defaults.
XLA_OWN = {"xla_backend_optimization_level": 3, "xla_cpu_use_fusion_emitters": True}


@pytest.fixture(scope="module")
def images():
    """{(backend, preset): rgb} of the test scene."""
    out = {}
    with pytest.MonkeyPatch.context() as m:
        m.setitem(xla.XLA_PRESETS, "default", {"cpu": XLA_OWN})
        for backend in ("jax", "fused"):
            for preset in ("default", "fast-compile"):
                out[backend, preset] = np.asarray(jr.render(_scene(), CAMERA, _settings(backend, preset)).rgb)
    return out


def test_the_suites_flags_are_the_fast_compile_preset_at_O0():
    """tests/conftest.py sets the CPU flags of "fast-compile" in $XLA_FLAGS (before JAX
    starts, so it cannot import jaxrt), with LLVM -O0: they must not drift from the
    preset."""
    from conftest import TEST_XLA_FLAGS

    preset = {**xla.XLA_PRESETS["fast-compile"]["cpu"], "xla_backend_optimization_level": 0}
    assert TEST_XLA_FLAGS == {k: str(v).lower() for k, v in preset.items()}
    assert XLA_OWN.keys() == preset.keys()


def test_xla_preset_is_validated_with_the_field_name():
    assert jr.KernelOptions().xla == "default"
    with pytest.raises(ValueError, match=r"RenderSettings\.kernel\.xla = 'fast', expected one of"):
        jr.KernelOptions(xla="fast")
    with pytest.raises(ValueError, match=r"RenderSettings\.kernel\.xla = 1, expected"):
        jr.RenderSettings(kernel={"xla": 1})
    assert jr.RenderSettings(kernel={"xla": "fast-compile"}).kernel.xla == "fast-compile"
    with pytest.raises(jr.config.ConfigError, match=r"settings\.kernel\.xla = 'O1', expected"):
        jr.config.check_settings({"kernel": {"xla": "O1"}}, "--set")
    with pytest.raises(ValueError, match=r"RenderSettings\.kernel\.xla = 'turbo'"):
        xla.compiler_options("turbo")


def test_presets_per_platform():
    """"default" is XLA's defaults everywhere; "fast-compile" names CPU flags only (a GPU
    compiles as before); of them, exactly those this XLA knows are passed, and LLVM's -O1
    is known to every supported one."""
    assert xla.XLA_PRESETS["fast-compile"] == {"cpu": FAST_CPU}
    assert xla.compiler_options(jr.RenderSettings()) == {}
    assert xla.compiler_options("fast-compile", platform="gpu") == {}
    known = {k: v for k, v in FAST_CPU.items() if _known(k, v)}
    assert known["xla_backend_optimization_level"] == 1
    assert xla.compiler_options("fast-compile", platform="cpu") == known
    assert xla.compiler_options(_settings("jax", "fast-compile")) == FAST


def test_an_unknown_flag_is_dropped_with_a_warning(monkeypatch):
    """A flag this XLA does not know (another jax version) is left out, the others kept,
    and rendering goes on."""
    known = {"xla_backend_optimization_level": 1}
    preset = {**known, "xla_cpu_flag_jaxrt_made_up": True}
    monkeypatch.setitem(xla.XLA_PRESETS, "fast-compile", {jax.default_backend(): preset})
    with pytest.warns(UserWarning, match="xla_cpu_flag_jaxrt_made_up"):
        assert xla.compiler_options("fast-compile") == known
    image = jr.render(_scene(), CAMERA, _settings("jax", "fast-compile"))
    assert np.all(np.isfinite(np.asarray(image.rgb)))


#: Compiles a small and a large while loop in a fresh process (jaxrt imported first, as a
#: script would) and prints $XLA_FLAGS and whether XLA:CPU hoisted each into one function.
_HOIST_PROBE = """
import os, jaxrt, jax, jax.numpy as jnp
def f(x):
    return jax.lax.while_loop(lambda c: c[0] < 9, lambda c: (c[0] + 1, jnp.sin(c[1])), (0, x))[1]
print(os.environ.get("XLA_FLAGS", ""))
for shape in [(16, 16), (1024, 512)]:  # 1 KiB and 2 MiB of state
    print("xla_cpu_small_call" in jax.jit(f).lower(jnp.ones(shape)).compile().as_text())
"""


def _hoist_probe(xla_flags):
    import os
    import subprocess
    import sys

    env = {**os.environ, "XLA_FLAGS": xla_flags, "JAX_PLATFORMS": "cpu"}
    run = subprocess.run([sys.executable, "-c", _HOIST_PROBE], env=env, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    flags, small, large = run.stdout.strip().splitlines()[-3:]
    return flags, small == "True", large == "True"


def test_import_keeps_xla_cpu_from_hoisting_a_large_while_into_one_function():
    """XLA:CPU compiles a `while` that accesses fewer bytes than its backend option
    `xla_cpu_small_while_loop_byte_threshold` as one LLVM function. On jax >= 0.12
    (whose default hoists both) importing jaxrt sets it to 1e6 in $XLA_FLAGS (merged with
    the flags there) before JAX reads them: a 1 KiB loop is still hoisted, a 2 MiB one is
    not. The defaults of jax 0.10 and 0.11 hoist neither, and jaxrt leaves them be. A
    value the user set is kept: with 1e9 bytes both are hoisted."""
    key = "xla_cpu_small_while_loop_byte_threshold"
    assert xla.PROCESS_OPTIONS == {key: "1000000"}
    new = jax.__version_info__ >= (0, 12)
    flags, small, large = _hoist_probe("--xla_cpu_enable_fast_math=false")
    ours = f" --xla_backend_extra_options={key}=1000000" if new else ""
    assert flags == "--xla_cpu_enable_fast_math=false" + ours
    assert (small, large) == (new, False)
    users = f"--xla_backend_extra_options={key}=1000000000"
    assert _hoist_probe(users) == (users, True, True)


def test_process_flags_come_too_late_once_jax_has_started():
    """Here JAX has started (the suite's renders): $XLA_FLAGS is read, so nothing is added,
    with a warning on jax >= 0.12 where the option matters."""
    jnp.ones(1).block_until_ready()
    environ = {"XLA_FLAGS": "--xla_cpu_enable_fast_math=false"}
    if jax.__version_info__ >= (0, 12):
        with pytest.warns(UserWarning, match="import jaxrt before the first JAX computation"):
            assert xla.add_process_flags(environ) == []
    else:
        assert xla.add_process_flags(environ) == []
    assert environ == {"XLA_FLAGS": "--xla_cpu_enable_fast_math=false"}


@pytest.mark.parametrize("backend", ["jax", "fused"])
def test_fast_compile_images_equal_default_to_rounding(images, backend):
    default, fast = images[backend, "default"], images[backend, "fast-compile"]
    assert default.max() > 0.1  # something lit
    np.testing.assert_allclose(fast, default, rtol=0, atol=2e-5)


def test_options_reach_the_compiler_and_are_part_of_the_cache_key(images, compiles):
    """`render` compiles with the preset's options; a new preset compiles again, a new
    parameter value does not; `compile_render` and `render_views` pass them too."""
    settings = _settings("jax", "fast-compile")
    jr.render(_scene(radius=0.45), CAMERA, settings).rgb.block_until_ready()  # fixture compiled it
    assert [c for c in compiles if "render" in c[0]] == []
    assert hash(settings) != hash(_settings("jax", "default"))
    f = compile_render(_scene(), CAMERA, settings)
    renders = [opts for name, opts in compiles if "render" in name]
    # With no options (a GPU) the program is the fixture's, which JAX may serve compiled.
    assert renders == [FAST] or (not FAST and renders == [])
    np.testing.assert_allclose(np.asarray(f(_scene(), CAMERA).rgb), images["jax", "fast-compile"],
                               rtol=0, atol=1e-6)
    cameras = jr.views.stack_cameras([CAMERA, CAMERA])
    jr.render_views(_scene(), cameras, settings).rgb.block_until_ready()
    views = [opts for name, opts in compiles if "render_views" in name]
    assert views == [FAST]
    jr.render_views(_scene(radius=0.4), cameras, settings).rgb.block_until_ready()
    assert len([n for n, _ in compiles if "render_views" in n]) == 1


def test_a_render_inside_a_larger_program_leaves_the_options_to_it(compiles):
    """Inside jit (and under grad) a render's options are the outer program's: no error
    about compiler options on an inner jit; `compile_collected` gathers them, also when
    JAX reuses the cached trace (no render runs then)."""
    settings = _settings("jax", "fast-compile")
    assert not xla.tracing()
    assert jax.jit(lambda x: xla.tracing() + x)(0) == 1
    traced = []

    @jax.jit
    def total(radius):
        traced.append(1)
        scene = jr.Scene(surface=S.Sphere(radius=radius, material=0),
                         materials=[jr.bsdf.Lambert(albedo=(0.5, 0.5, 0.5))], lights=[])
        return jnp.sum(jr.render(scene, CAMERA, settings).rgb)

    r = jnp.float32(0.5)
    first = xla.compile_collected(total, r)
    second = xla.compile_collected(total, r)
    assert len(traced) == 1  # the second lowering reused the trace: nothing was noted
    assert [opts for name, opts in compiles if "total" in name] == [FAST]  # compiled once
    assert float(first(r)) == float(second(r))
    assert xla.lower_collected(total, r)[1] == FAST


def test_fit_step_compiles_with_the_losses_options(compiles):
    """The optax step (`fit._Step`) of a loss that renders gets that render's options."""
    settings = _settings("jax", "fast-compile")
    target = jnp.full((CAMERA.height, CAMERA.width, 3), 0.2)

    def loss(p, _):
        scene = jr.Scene(surface=S.Sphere(radius=p, material=0),
                         materials=[jr.bsdf.Lambert(albedo=(0.5, 0.5, 0.5))],
                         lights=[jr.DirectionalLight(direction=(0.0, 0.0, -1.0), irradiance=(2.0,) * 3)])
        return jr.fit.l2_loss(jr.render(scene, CAMERA, settings).rgb, target)

    result = jr.fit.fit(loss, jnp.float32(0.6), jr.fit.adam(0.01), max_steps=2, progress=False)
    assert np.isfinite(result.loss)
    steps = [opts for name, opts in compiles if "optax_step" in name]
    assert steps == [FAST]


def test_cli_compiles_with_the_librarys_options_unless_told(tmp_path, capsys, compiles):
    over = parse_overrides(["kernel.xla=fast-compile", "kernel.unroll=2", "spp=2"])
    assert over == {"kernel": {"xla": "fast-compile", "unroll": 2}, "spp": 2}
    with pytest.raises(_Failure, match="unknown kernel option `speed`"):
        parse_overrides(["kernel.speed=3"])
    with pytest.raises(_Failure, match="unknown setting `camera.fov`"):
        parse_overrides(["camera.fov=3"])
    config = tmp_path / "ball.toml"
    config.write_text('[camera]\neye = [0.0, 0.0, -4.0]\ntarget = [0.0, 0.0, 0.0]\nwidth = 6\n'
                      'height = 4\n[settings]\nbackend = "jax"\naovs = []\n[materials.white]\n'
                      'type = "lambert"\n[surface]\ntype = "sphere"\nradius = 1.0\n')
    for args, preset, options in (([], "default", {}),
                                  (["--set", "kernel.xla=fast-compile"], "fast-compile", FAST)):
        compiles.clear()
        assert main(["render", str(config), "-o", str(tmp_path / "ball"), "--no-cache", *args]) == 0
        assert f"xla {preset}" in capsys.readouterr().out
        assert [opts for name, opts in compiles if "render" in name] == [options]
