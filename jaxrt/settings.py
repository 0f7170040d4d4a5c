"""RenderSettings: every accuracy/speed dial of the renderer, with its default and meaning."""

import dataclasses

from .xla import XLA_PRESETS

_NORMAL_MODES = ("autodiff", "central", "tetrahedron")
_SHADOW_MODES = ("none", "hard", "soft")
_DTYPES = ("float32", "float64")
_BACKENDS = ("jax", "fused", "pallas", "auto")
_ROOT_SOLVERS = ("newton", "optimistix")
_RECURSIONS = ("auto", "unrolled", "scan")
_SPLITS = ("columns", "rows")
_SILHOUETTE_GRADIENTS = ("ramp", "outline")
AOVS = ("depth", "normal", "albedo", "steps", "coverage")
#: Rays per tile of `batch_size = "auto"`: on a CPU, tiles that stay in cache; on a GPU,
#: tiles large enough to fill it (a 480×270 image is one tile) that bound the memory of
#: very large images.
CPU_TILE_RAYS = 4096
#: ... and of the "fused" lane kernels on a CPU: 32×32 tiles, so that a slot of the ray
#: tree that no ray of a tile needs is skipped at a finer grain (showcase 480×270, 2 cores:
#: 18.0 s in tiles of 4096, 12.2 s of 1024; the Warp scene the same, 3.2–3.5 s).
CPU_LANE_TILE_RAYS = 1024
GPU_TILE_RAYS = 1 << 18


@dataclasses.dataclass(frozen=True)
class KernelOptions:
    """How the fused lane backends ("fused", "pallas"; `jaxrt.kernels.fused`) build their
    programs: switches that change the compiled kernel, not the image (beyond rounding,
    and for the Pallas fast-math forms a few ulps). A field of `RenderSettings`
    (`kernel`), so they are part of the jit cache key: changing one recompiles. In TOML,
    `[settings.kernel]` with any of these keys (`--set kernel={unroll=2}`).

      interpret          Pallas interpret mode: None (default) = only without a GPU
                         (tests); False forces the Triton lowering (to check it on a
                         machine without a GPU: lower for platform "cuda").
      pallas_num_warps   warps per Pallas program instance (Triton's num_warps); None:
                         one warp per 64 rays, 1 to 4.
      unroll             loop iterations of the one-ray program per test of a block's
      pallas_unroll      loop condition (a reduction over the block; inactive lanes keep
                         their state either way), for "fused" and "pallas". On an H200
                         (Warp scene, 2048×1024, rgb only) 2 rendered in 0.280 ms
                         against 0.300 ms for 1 (same run): the test is a
                         14-instruction warp reduction, against about 50 for a march step.
      materialize        "fused" on XLA: materialise function results outside loops
                         (`lanes.control._barrier`). On a 2-core Sapphire Rapids with jax 0.10.2
                         this made "fused" 3× faster on the Warp scene.
      compaction         "fused" on XLA: a loop whose condition varies between rays
                         (a march) runs on the whole tile until at most 1/compaction
                         of its rays are active, then on those rays alone, gathered
                         into a narrow block (`lanes.control._compacted`); 1: on the
                         whole tile until its slowest ray is done. Same results.
      pallas_fma         fuse a product used once by an add or sub into a fused
                         multiply-add (PTX `fma.rn.f32`: one rounding instead of two;
                         Triton as JAX drives it does not contract them itself).
      pallas_uniforms    read the values shared by all rays (functions of the
                         parameters alone, outside loops) from a vector computed once
                         before the kernel (`lanes.Uniforms`), not in every thread.
      pallas_scan_loops  keep a scan over the kernel's parameters (a stacked union's
                         children, at least `lanes.control.LOADED_SCAN_MIN` of them) as
                         one loop that loads iteration i's values
                         (`lanes.control._scan_loaded`), not n copies of its body; the
                         program's gradients of the SDF are then taken in forward mode
                         (`trace.value_and_gradient`). False: every scan unrolled.
      pallas_fast_math   per-ray sqrt, rsqrt, division, exp, log and pow as PTX's
                         approximate instructions (what CUDA's --use_fast_math compiles;
                         pow of a negative base is NaN), division by shared values as a
                         multiplication. On the Warp scene it moved a few pixels by up
                         to 3.4e-3 and rendered in 0.304 ms instead of 0.332 ms (H200).
      auto_max_lane_ops_fused, auto_max_lane_ops_pallas
                         backend "auto" renders one-ray programs of more lane operations
                         than this (`kernels.fused._lane_ops`: elementwise operations,
                         times the rays of the batched levels of a ray tree; an
                         operation on the scene's values alone counts once) with
                         "jax": their compile time grows with it, Triton's faster than
                         linearly. Counted as Pallas does (with pallas_scan_loops, a
                         stacked union's scan once, other scans once per iteration):
                         the Warp scene 3.0k, 8, 64 or 256 spheres on a plane 2.5k
                         (Pallas compiles the 64 in 7 s and renders them in 2.7 ms at
                         512×512 on an H100; unrolled, 14.7k: 85 s and 4.2 ms), the
                         showcase 127k with its tree as a scan and 113k unrolled, the
                         glass scene 806k / 465k at max_depth 6.
                         Counted as "fused" does (phases): Warp 2.2k, showcase 13k
                         ("fused": 33 s on 2 CPU cores), glass 6.3k ("fused": 20 s at
                         16×12).
      pallas_block       rays per Pallas program instance when batch_size does not say
                         otherwise (`fused.pallas_block`): a 4×8 tile on one warp. On an
                         H100 (Warp scene) 0.431 ms against 0.475 ms for 16×16 tiles on
                         four warps.
      march_form         the loop form of the marches in the one-ray program of
                         "fused" and "pallas" (`jaxrt.march.form`): "phases" (one copy
                         of the scene SDF per march: each march's start, steps and
                         finish are phases of one loop), "plain" (start before the
                         loop, finish after it, Newton polish and origin settling as
                         straight code), or "auto" (default): "plain" for one-ray
                         programs of at most plain_max_lane_ops, "phases" for larger
                         ones. The "jax" path always takes the phases.
      plain_max_lane_ops "auto" takes the plain form for one-ray programs of at most
                         this many lane operations (`kernels.fused._lane_ops` of both
                         traces: a stacked group counts the same for any number of rows
                         on "fused"). The plain form renders faster (Warp scene, "fused",
                         1024×512 on 2 CPU cores: 0.60 s against 2.47 s; the showcase
                         7.3 s against 14.9 s at 480×270) but a large program compiles
                         for longer in it (the showcase: 70 s against 35 s), and
                         Triton's compile time grows much faster than the program: on
                         an H200 (jax 0.11.2) the Warp scene's plain
                         program (3.2k; 2.4k in phases) compiles in about 5 s and
                         renders 2× faster than its phases; the 64-sphere union of
                         experiments/bench/gradients.py (9.7k plain, 6.7k in phases)
                         compiled its forward in 347 s plain (4.4 ms a render at
                         512×512) against 111 s in phases (4.5 ms).
      replay_gather      rays per batch in which the replay of a "fused" gradient
                         (`render._replay`) shades the secondary rays of an RGB ray
                         tree (a level of it, or a slot with `recursion = "scan"`),
                         only the batches that hold rays alive there
                         (`march.tape._gathered`); 0: every ray of the tree for every
                         pixel. The showcase's value_and_grad at 64×36 on 2 CPU cores:
                         2.46× its forward with 0, 1.5× with 128–512.
      replay_wide_unions a gradient's replay evaluates every child of a stacked union
                         at once (`vmap`) and takes the nearest, instead of a scan
                         over them (`sdf.stack.stacked_eval`); None (default): on a
                         GPU, where each iteration of a scan is kernels of their own
                         (64 spheres, 512×512, H100: value_and_grad 9.4 → 4.9 ms).
      replay_kernel      a gradient (reverse mode) differentiates the replay in a
                         lane kernel of its own ("fused" tiles, or one Pallas kernel),
                         each sample's VJP of its replay summed over the samples
                         (`render._recorded_vjp`), instead of XLA's reverse pass of the
                         vmapped replay. No forward mode (`jax.jvp`) then: set it
                         false for that. None (default): on Pallas, for VJP programs of
                         at most replay_kernel_max_lane_ops (`kernels.fused._lane_ops`).
                         The Warp scene at 2048×1024 on an H100: value_and_grad 3.21 →
                         1.31 ms (1.59× its forward), temporaries 778 → 243 MB. On 2
                         CPU cores ("fused") about as fast as XLA's reverse pass, with
                         a fifth of its temporaries, and slower to compile: off.
      replay_kernel_max_lane_ops
                         the largest VJP program that replay_kernel = None runs in a
                         kernel: the Warp scene's is 2.9k lane operations (Triton
                         compiles it in seconds); 64 stacked spheres' 13.5k (the
                         reverse scan over the children is unrolled; on an H100 their
                         gradient had not compiled after 200 s).
      xla                the XLA compiler options of every backend's render program
                         (`jaxrt.xla.XLA_PRESETS`): "default" (XLA's) or "fast-compile"
                         (on a CPU: the legacy loop emitter instead of XLA's MLIR
                         fusion emitters, `xla_cpu_use_fusion_emitters = False`, and
                         LLVM -O1, `xla_backend_optimization_level = 1`; nothing on a
                         GPU). No fast math. The showcase on 2 shared CPU cores (jax
                         0.10.2, 96×54): XLA's compile 1.3–2.3× faster in wall seconds
                         (CPU seconds: 1.55× "fused", 2.1× "jax"), rendering 4–23 %
                         ("fused") and 6–80 % ("jax") slower; value_and_grad (32×24)
                         compiled 1.04–2.3× faster, its step −19 % to +35 %
                         (docs/performance.md, "XLA compiler options"). Images agree
                         with "default" to rounding except at pixels that "default"
                         itself renders unstably (there). The library and the
                         `jaxrt render` command use "default" (`--set
                         kernel.xla=fast-compile` for the preset).
    """

    interpret: bool | None = None
    pallas_num_warps: int | None = None
    unroll: int = 1
    pallas_unroll: int = 2
    materialize: bool = True
    compaction: int = 16
    pallas_fma: bool = True
    pallas_uniforms: bool = True
    pallas_scan_loops: bool = True
    pallas_fast_math: bool = True
    auto_max_lane_ops_fused: int = 60_000
    auto_max_lane_ops_pallas: int = 20_000
    pallas_block: int = 32
    march_form: str = "auto"
    plain_max_lane_ops: int = 5000
    replay_gather: int = 256
    replay_wide_unions: bool | None = None
    replay_kernel: bool | None = None
    replay_kernel_max_lane_ops: int = 5000
    xla: str = "default"

    def __post_init__(self):
        def need(ok, field, expected):
            if not ok:
                value = getattr(self, field)
                raise ValueError(f"RenderSettings.kernel.{field} = {value!r}, expected {expected}")

        need(self.interpret is None or isinstance(self.interpret, bool), "interpret",
             "true, false or None")
        need(self.pallas_num_warps is None or (_is_int(self.pallas_num_warps)
                                               and self.pallas_num_warps in (1, 2, 4, 8, 16)),
             "pallas_num_warps", "None or a power of two in [1, 16]")
        need(_is_int(self.unroll) and self.unroll >= 1, "unroll", "an integer ≥ 1")
        need(_is_int(self.pallas_unroll) and self.pallas_unroll >= 1, "pallas_unroll",
             "an integer ≥ 1")
        need(_is_int(self.compaction) and self.compaction >= 1, "compaction", "an integer ≥ 1")
        need(_is_int(self.replay_gather) and self.replay_gather >= 0, "replay_gather",
             "an integer ≥ 0")
        for name in ("replay_wide_unions", "replay_kernel"):
            need(getattr(self, name) is None or isinstance(getattr(self, name), bool), name,
                 "true, false or None")
        for name in ("materialize", "pallas_fma", "pallas_uniforms",
                     "pallas_scan_loops", "pallas_fast_math"):
            need(isinstance(getattr(self, name), bool), name, "true or false")
        for name in ("auto_max_lane_ops_fused", "auto_max_lane_ops_pallas", "plain_max_lane_ops",
                     "replay_kernel_max_lane_ops"):
            need(_is_int(getattr(self, name)) and getattr(self, name) >= 0, name,
                 "an integer ≥ 0")
        need(_is_int(self.pallas_block) and 16 <= self.pallas_block <= 256, "pallas_block",
             "an integer in [16, 256] (rounded down to a power of two)")
        need(self.march_form in ("auto", "phases", "plain"), "march_form",
             '"auto", "phases" or "plain"')
        need(isinstance(self.xla, str) and self.xla in XLA_PRESETS, "xla",
             f"one of {sorted(XLA_PRESETS)} (jaxrt.xla.XLA_PRESETS)")

    def auto_max_lane_ops(self, backend):
        """The "auto" size limit for the fused `backend` ("fused" or "pallas")."""
        return {"fused": self.auto_max_lane_ops_fused,
                "pallas": self.auto_max_lane_ops_pallas}[backend]

    def replace(self, **changes):
        """A copy with some options changed (validated)."""
        return dataclasses.replace(self, **changes)


@dataclasses.dataclass(frozen=True)
class RenderSettings:
    """Accuracy and speed dials. All are static: changing one recompiles, changing a
    scene parameter value never does.

    Marching
      max_steps        step budget of a sphere-traced ray (primary and secondary).
      hit_epsilon      absolute hit threshold in world units: a ray hits when the
                       (Lipschitz-scaled) distance falls below it.
      pixel_epsilon    hit threshold relative to the pixel footprint: the effective
                       epsilon is hit_epsilon + pixel_epsilon · r(t), r(t) the radius of
                       the pixel cone at distance t (0 switches it off).
      max_distance     rays that travel this far miss, but for the planes at the top of
                       the scene's union, which are also intersected analytically
                       (notes, "ray–plane"; `analytic_planes`, default True): a floor
                       reaches the horizon (up to 10⁴·max_distance) instead of ending
                       in a circle of radius max_distance. Only rays that escaped, or
                       ran out of budget gliding along the plane, meet it there (the
                       `analytic_planes` field).
      over_relaxation  ω of Keinert et al. 2014 "Enhanced Sphere Tracing" (1 = plain
                       sphere tracing; 1.2–1.8 take longer steps with a safe fall-back).
      newton_steps     Newton polishing steps at a hit (they also carry the implicit-
                       function gradient of the hit point; at least 1 when gradients
                       are wanted). The second step makes near-grazing hits accurate:
                       one step leaves an error ~ ε²/cos³ (cos between ray and
                       normal), 1.7e-4 relative at 0.8° from tangent in float32.
      root_solver      how the hit is polished and differentiated: "newton" (a
                       hand-written Newton step whose slope is held constant, default)
                       or "optimistix" (`optimistix.root_find`, Newton with
                       `ImplicitAdjoint`, newton_steps steps, throw=False). Both give
                       dt/dθ = −(∂f/∂θ + ∇f·∂(o + t d)/∂θ) / (∇f·d); see `jaxrt.trace`.
    Shading
      normal_mode      "autodiff" (gradient of the SDF, default), "central"
                       (6 evaluations) or "tetrahedron" (4 evaluations).
      normal_epsilon   finite-difference step of the "central"/"tetrahedron" normals.
      shadows          "hard" (a traced shadow ray), "soft" (penumbra estimate of
                       Quilez, k·d/t along the shadow ray) or "none".
      shadow_steps     step budget of a shadow ray.
      penumbra         k of the soft shadow: larger is sharper.
      penumbra_refine_steps  golden-section steps that refine the soft shadow's sampled
                       penumbra minimum (`march.shadow.SoftShadow.refine_steps`): its
                       envelope gradient is then that of a stationary minimum (0.25 %
                       of finite differences against 2–5 % unrefined); 0 takes Quilez's
                       sampled minimum as it is, as Warp's example does (the Warp scene
                       on 2 CPU cores renders about 1.8× faster).
      shadow_max_distance  shadow rays towards directional lights stop here
                       (None: max_distance); towards point lights at the light.
      max_depth        Whitted recursion depth (reflected/refracted rays); only used
                       when the scene has specular materials.
      recursion        how the ray tree is compiled (`jaxrt.integrator`): "unrolled"
                       (one vmapped batch per level, compile time grows with
                       max_depth), "scan" (one `lax.scan` over the tree's slots in
                       heap order: one compiled shading step whatever max_depth, the
                       same images) or "auto" (default: `ray_tree_form`, "unrolled" on
                       a GPU and "scan" elsewhere).
      ray_offset       secondary rays start ray_offset · (ε + 8 ulp·max|pᵢ|) off the
                       surface (multiples of the hit epsilon plus the rounding error of
                       p; `integrator.spawn_offset`); must exceed 1 to leave the ε band.
      spawn_steps      Newton steps that settle a secondary ray's origin on the level
                       set f = ±offset (`integrator.spawn_origin`): two clear the edges
                       and corners of boxes, where another face is nearer than the
                       offset; 0 starts at p + offset·n (shadow acne along edges).
    Sampling
      spp              samples per pixel, stratified (N-rooks) with a fixed seed,
                       averaged with a box filter; 1 = pixel centres.
      seed             seed of the pixel jitter.
      wavelengths      wavelength samples in spectral mode (0 = RGB rendering; only
                       scenes with a dispersive material use more than 0).
    Numerics and execution
      dtype            "float32" (default) or "float64" (needs jax_enable_x64).
      batch_size       rays per tile: tiles are traced one after another and each
                       stops as soon as its rays are done (None: whole image at once;
                       "auto", the default: CPU_TILE_RAYS on a CPU (CPU_LANE_TILE_RAYS
                       for "fused"), GPU_TILE_RAYS on a GPU, where tiles run one after
                       another as separate kernel launches: the showcase at 480×270 with backend "jax" rendered
                       in 341 ms in tiles of 4096 against 20.5 ms whole, H200,
                       jax 0.11.2; `rays_per_tile`).
      backend          how the per-ray program is batched: "auto" (default: "pallas" on
                       a GPU, "fused" elsewhere; falls back to "jax", with a one-line
                       warning, for any program that lanes cannot run or that would
                       take long to compile), "fused" (the program scalarised into one
                       lane per ray and run by XLA in tiles, `jaxrt.kernels`),
                       "pallas" (the same lanes inside one Pallas GPU kernel; interpret
                       mode without a GPU) or "jax" (vmap over rays, the reference).
                       Gradients: "jax" differentiates its own program; the others
                       record their marches in the kernel and differentiate a
                       loop-free replay of the program (`jaxrt.render`, same
                       gradients to rounding).
      aovs             the AOVs that `render` returns besides rgb (a subset of
                       depth, normal, albedo, steps, coverage; the others are None in
                       the Image). Fewer AOVs: less memory written per pixel (the
                       fused kernels store only these), e.g. aovs=() for rgb only.
      devices          local devices to shard the image's rows over (`jaxrt.sharding`;
                       1: no sharding, default; 0: all local devices).
      split            the image axis cut into one block per device: "columns"
                       (default) or "rows".
      threads          CPU threads of a render called outside a trace (0: one per
                       core, default; 1: one call): XLA:CPU runs a render program on
                       one core, so blocks of rows are rendered at once, each a call
                       of one compiled program (`jaxrt.render.block_rows`); with
                       devices = 1 only, on a CPU. Gradients, and renders inside a
                       jit, are one program on one core (shard them with devices).
      kernel           `KernelOptions`: how the fused lane backends build their
                       kernels (unroll, Pallas warps and fast math, "auto"'s size
                       limits, ...).
      silhouette       silhouette-aware pixel coverage (`jaxrt.silhouette`). Off
                       (default), every sample is a point sample: an outline moving
                       across a pixel changes it by a jump, so the gradient of any
                       image loss with respect to where outlines are (a sphere's
                       radius or centre seen against what lies behind it) is ZERO; only
                       shading inside the outlines is differentiated. On, each sample
                       whose ray passes within 2·silhouette_width pixels outside an
                       outline blends the surface it nearly missed over what it sees,
                       with a coverage α that falls smoothly from 1 at the outline to
                       0 at 2·silhouette_width pixels from it (its distance measured
                       from the ray's closest approach). This antialiases outlines and
                       gives them gradients. Bias: outlines are dilated by
                       silhouette_width pixels on average (images rendered with the
                       same settings are dilated alike, so fits to them are not
                       biased); the gradient of an image region's mean is exact to
                       first order (within 5 % of finite differences of 32×32-sample
                       renders in the tests), except at shading discontinuities inside
                       an outline (creases, shadow edges), which still get none; one
                       near miss per sample. Costs about 2.5× the render time.
      silhouette_width the width W of the coverage ramp, in pixels (the ramp spans
                       2W; divided by sqrt(spp) when there are several samples per
                       pixel). W ≥ 1 at 1 spp keeps the ramp's derivative summing to
                       1 along every row of pixels an outline crosses.
      silhouette_gradient where the estimator puts the derivative of an outline's
                       position: "ramp" (default) on the ramp's samples, 0 to
                       2·silhouette_width pixels outside the outline, the exact
                       derivative of the estimator's own (dilated) image; "outline" on
                       the pixels the outline crosses (`silhouette.splat_outline`),
                       that of a box-filtered image. Pick "outline" when the loss's
                       values are box-filtered (a photograph, or a straight-through
                       loss with the values of a silhouette-free render): a ramp
                       sample weighs the outline's derivative with the residual 1–2
                       pixels outside the outline, where an object that is too large
                       has none, so it shrinks far too weakly (docs/inverse.md).
    """

    max_steps: int = 128
    hit_epsilon: float = 1e-4
    pixel_epsilon: float = 0.0
    max_distance: float = 100.0
    over_relaxation: float = 1.0
    newton_steps: int = 2
    normal_mode: str = "autodiff"
    normal_epsilon: float = 1e-4
    shadows: str = "hard"
    shadow_steps: int = 64
    penumbra: float = 8.0
    penumbra_refine_steps: int = 8
    shadow_max_distance: float | None = None
    max_depth: int = 2
    ray_offset: float = 4.0
    spawn_steps: int = 2
    spp: int = 1
    seed: int = 0
    wavelengths: int = 0
    dtype: str = "float32"
    batch_size: int | str | None = "auto"
    backend: str = "auto"
    devices: int = 1
    threads: int = 0
    silhouette: bool = False
    silhouette_width: float = 1.0
    silhouette_gradient: str = "ramp"
    root_solver: str = "newton"
    recursion: str = "auto"
    aovs: tuple = AOVS
    # Planes at the top of the scene's union are also intersected analytically
    # (integrator.analytic_planes, integrator._meet_planes): a floor reaches the horizon
    # instead of ending at max_distance. Met by a ray that did not hit: one that escaped
    # at max_distance, or one out of budget gliding along the plane (the plane the
    # nearest surface at its last sample, f there = the plane's distance to rounding,
    # the plane's t beyond that sample). Not met by a ray out of budget nearer another
    # surface (past a near miss: it stays a miss, issue 14), nor by rays starting inside
    # a solid. Not seen: an object beyond max_distance before the floor, or one standing
    # on the floor ahead of a gliding ray out of budget (the rest of its path is not
    # marched). False: planes are only sphere-traced, like every other shape.
    analytic_planes: bool = True
    # The image axis cut into one block per device when devices != 1 (`jaxrt.sharding`):
    # "columns" (default: left and right of a frame usually march alike, top and
    # bottom do not) or "rows".
    split: str = "columns"
    # How the fused lane backends build their kernels (`KernelOptions`; in the cache
    # key like every field). A {key: value} table (TOML) is read as KernelOptions(**table).
    kernel: KernelOptions = dataclasses.field(default_factory=KernelOptions)

    def __post_init__(self):
        def need(ok, field, expected):
            if not ok:
                value = getattr(self, field)
                raise ValueError(f"RenderSettings.{field} = {value!r}, expected {expected}")

        need(_is_int(self.max_steps) and self.max_steps >= 1, "max_steps", "an integer ≥ 1")
        if isinstance(self.aovs, list):  # from TOML
            object.__setattr__(self, "aovs", tuple(self.aovs))
        need(isinstance(self.aovs, tuple) and set(self.aovs) <= set(AOVS)
             and len(set(self.aovs)) == len(self.aovs), "aovs",
             f"distinct names among {AOVS}")
        need(_is_num(self.hit_epsilon) and self.hit_epsilon > 0, "hit_epsilon", "a number > 0")
        need(_is_num(self.pixel_epsilon) and self.pixel_epsilon >= 0, "pixel_epsilon", "a number ≥ 0")
        need(_is_num(self.max_distance) and self.max_distance > 0, "max_distance", "a number > 0")
        need(
            _is_num(self.over_relaxation) and 1 <= self.over_relaxation < 2,
            "over_relaxation",
            "a number in [1, 2)",
        )
        need(_is_int(self.newton_steps) and self.newton_steps >= 0, "newton_steps", "an integer ≥ 0")
        need(self.normal_mode in _NORMAL_MODES, "normal_mode", f"one of {_NORMAL_MODES}")
        need(_is_num(self.normal_epsilon) and self.normal_epsilon > 0, "normal_epsilon", "a number > 0")
        need(self.shadows in _SHADOW_MODES, "shadows", f"one of {_SHADOW_MODES}")
        need(_is_int(self.shadow_steps) and self.shadow_steps >= 1, "shadow_steps", "an integer ≥ 1")
        need(_is_num(self.penumbra) and self.penumbra > 0, "penumbra", "a number > 0")
        need(_is_int(self.penumbra_refine_steps) and self.penumbra_refine_steps >= 0,
             "penumbra_refine_steps", "an integer ≥ 0")
        need(
            self.shadow_max_distance is None
            or (_is_num(self.shadow_max_distance) and self.shadow_max_distance > 0),
            "shadow_max_distance",
            "a number > 0 or None",
        )
        need(_is_int(self.max_depth) and 0 <= self.max_depth <= 16, "max_depth", "an integer in [0, 16]")
        need(_is_num(self.ray_offset) and self.ray_offset > 1, "ray_offset",
             "a number > 1 (the offset must leave the band |f| < ε)")
        need(_is_int(self.spawn_steps) and self.spawn_steps >= 0, "spawn_steps", "an integer ≥ 0")
        need(self.recursion in _RECURSIONS, "recursion", f"one of {_RECURSIONS}")
        need(_is_int(self.spp) and self.spp >= 1, "spp", "an integer ≥ 1")
        need(_is_int(self.seed), "seed", "an integer")
        need(_is_int(self.wavelengths) and self.wavelengths >= 0, "wavelengths", "an integer ≥ 0")
        need(self.dtype in _DTYPES, "dtype", f"one of {_DTYPES}")
        need(
            self.batch_size is None or self.batch_size == "auto"
            or (_is_int(self.batch_size) and self.batch_size >= 1),
            "batch_size",
            'an integer ≥ 1, "auto" or None',
        )
        need(isinstance(self.silhouette, bool), "silhouette", "true or false")
        need(self.backend in _BACKENDS, "backend", f"one of {_BACKENDS}")
        need(_is_int(self.devices) and self.devices >= 0, "devices", "an integer ≥ 0 (0: all)")
        need(_is_int(self.threads) and self.threads >= 0, "threads", "an integer ≥ 0 (0: one per core)")
        need(
            _is_num(self.silhouette_width) and 0 < self.silhouette_width <= 16,
            "silhouette_width",
            "a number in (0, 16] (pixels)",
        )
        need(self.silhouette_gradient in _SILHOUETTE_GRADIENTS, "silhouette_gradient",
             f"one of {_SILHOUETTE_GRADIENTS}")
        need(self.root_solver in _ROOT_SOLVERS, "root_solver", f"one of {_ROOT_SOLVERS}")
        need(isinstance(self.analytic_planes, bool), "analytic_planes", "true or false")
        need(self.split in _SPLITS, "split", f"one of {_SPLITS}")
        if isinstance(self.kernel, dict):  # from TOML or --set
            unknown = sorted(set(self.kernel) - {f.name for f in dataclasses.fields(KernelOptions)})
            if unknown:
                raise ValueError(f"RenderSettings.kernel.{unknown[0]} = {self.kernel[unknown[0]]!r}, "
                                 f"expected a KernelOptions field, one of "
                                 f"{[f.name for f in dataclasses.fields(KernelOptions)]}")
            object.__setattr__(self, "kernel", KernelOptions(**self.kernel))
        need(isinstance(self.kernel, KernelOptions), "kernel", "a KernelOptions (or a table of its fields)")

    def ray_tree_form(self):
        """How the ray tree is compiled: `recursion`, with "auto" → "unrolled" on a GPU
        and "scan" elsewhere. Read at trace time (the platform is part of every jit cache
        key). On 2 CPU cores "scan" compiles and renders faster on every backend: the
        showcase on "fused" at 64×36, max_steps 64, in one run, compiled in 28 s and
        rendered in 85 ms against 53 s and 1025 ms unrolled (a tile of rays skips the
        slots dead in all of them), its value_and_grad in 73 s and 126 ms against 148 s
        and 1042 ms; the glass scene (depth 6, 160×120) on "jax" in 10.8 s and 9.5 s
        against 49.3 s and 18.2 s. On
        an H200 "unrolled" renders faster (glass scene 139 ms against 542 ms; the
        showcase's gradient 152 ms against 215 ms on an H100) but compiles for longer
        (67.7 s against 6.4 s): a short session on a GPU may ask for "scan"."""
        if self.recursion != "auto":
            return self.recursion
        import jax

        return "unrolled" if jax.default_backend() == "gpu" else "scan"

    def rays_per_tile(self, n, lanes=False):
        """Rays per tile for `n` rays: `batch_size` capped at `n` (None: `n`; "auto":
        `CPU_TILE_RAYS`, or `CPU_LANE_TILE_RAYS` for the `lanes` kernels, on a CPU;
        `GPU_TILE_RAYS` on a GPU). Read at trace time: the platform is part of every jit
        cache key already."""
        b = self.batch_size
        if b == "auto":
            import jax

            if jax.default_backend() == "gpu":
                b = GPU_TILE_RAYS
            else:
                b = CPU_LANE_TILE_RAYS if lanes else CPU_TILE_RAYS
        return n if b is None else min(int(b), n)

    def replace(self, **changes):
        """A copy with some dials changed (validated)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def preset(cls, name, base=None, **changes):
        """Named points on the speed/accuracy front (`PRESETS`; measured by
        experiments/speed_accuracy.py): "fast", "balanced" or "reference".

        A preset sets only accuracy/speed dials (epsilons, budgets, Newton steps,
        samples, precision, backend); the dials that describe a scene's look (shadow
        mode, penumbra, max_distance, max_depth, ...) come from `base` (default:
        `RenderSettings()`, or a scene file's settings). `changes` are applied last.
        """
        if name not in PRESETS:
            raise ValueError(f"RenderSettings.preset({name!r}): expected one of {sorted(PRESETS)}")
        base = cls() if base is None else base
        return base.replace(**{**PRESETS[name], **changes})


def _is_int(x):
    return isinstance(x, int) and not isinstance(x, bool)


def _is_num(x):
    """A finite int or float (inf and NaN are not dials: an infinite epsilon hits at t = 0,
    an infinite max_distance lets a miss march until its budget runs out)."""
    return isinstance(x, (int, float)) and not isinstance(x, bool) and abs(x) < float("inf")


#: The presets of `RenderSettings.preset`: accuracy/speed dials only.
#:   fast       previews: an epsilon of one pixel footprint, small budgets, no Newton
#:              polish (so no hit-point gradients), fused lanes (Pallas on a GPU).
#:   balanced   a quarter-pixel epsilon (rays that graze far surfaces converge: with an
#:              absolute epsilon alone they exhaust any budget), one Newton step.
#:   reference  converged images for tests and error curves (float64, slow).
#: Claimed error (RMSE of linear RGB against "reference"), the dials alone (both at 16
#: spp) on the scene of tests/test_presets.py: fast ≤ 0.035 (measured 0.025), balanced
#: ≤ 0.01 (measured 0.006). Their place on the speed/accuracy front of three scenes:
#: experiments/speed_accuracy.py.
PRESETS = {
    "fast": dict(hit_epsilon=1e-4, pixel_epsilon=1.0, max_steps=96, newton_steps=0,
                 shadow_steps=32, spp=1, dtype="float32", backend="auto"),
    "balanced": dict(hit_epsilon=1e-4, pixel_epsilon=0.25, max_steps=256, newton_steps=1,
                     shadow_steps=64, spp=1, dtype="float32", backend="auto"),
    "reference": dict(hit_epsilon=1e-7, pixel_epsilon=0.0, max_steps=2048, newton_steps=2,
                      shadow_steps=2048, spp=16, dtype="float64", backend="jax"),
}

#: The bounds that tests/test_presets.py checks (RMSE against "reference", at 16 spp).
PRESET_CLAIMS = {"fast": 0.035, "balanced": 0.01}
