"""Typed configuration: one pydantic model per config section, the single source of every default.

* The sections with fixed keys have a model here: the run keys (:class:`RunConfig`),
  ``render`` (+ ``render.occupancy``), ``reconstruct``, ``stylize``, ``export``,
  ``trainer`` and ``experiment`` (every loss weight). Each field has its type, its
  default, its range and a description (units, what 0 / null means). ``conf/`` does
  not repeat them: :func:`~nerfart_plugin.config.compose.register_schema` stores their
  defaults in Hydra's ConfigStore as ``nerfart_schema``, the first entry of
  ``conf/config.yaml``'s defaults list, so presets, experiments and command-line
  overrides compose on top of it, ``--cfg job`` prints it and ``--help`` lists every
  field with its description.
* The component sections (``data``, ``backbone``, ``encoding``, ``guidance``) are typed as the ``Config``
  declared beside the component their ``name`` picks (:mod:`nerfart_plugin.config.sections`), so a registered
  custom component is checked and typed the same way.
* :func:`nerfart_plugin.config.validate.parse_config` is the one validation of a config; fields declared with
  ``changes_results=False`` are left out of the cache keys (:func:`~nerfart_plugin.config.validate.result_settings`).

Unknown or misspelled keys are refused (``extra="forbid"``) with the closest valid
key (difflib). Numbers must be finite; booleans are not numbers.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal, Optional, Union

from pydantic import BaseModel, BeforeValidator, Field, PrivateAttr, SerializeAsAny, field_validator

from nerfart_plugin.config.components import ComponentConfig
from nerfart_plugin.config.sections import TOP_LEVEL, typed_section
from nerfart_plugin.config.types import Color, Float, Fraction, Int, PathText, Seed, Setting, SettingsModel

__all__ = [
    "RunConfig", "RenderConfig", "OccupancyConfig", "ReconstructConfig", "StylizeConfig", "ExportConfig",
    "TrainerConfig", "ExperimentConfig", "LoggerConfig", "RegionConfig", "SECTIONS",
]

#: samples (rays x samples per ray) of one training step with grad: far beyond any GPU's memory above this
MAX_GRAD_SAMPLES = 2**24
#: samples of one no-grad chunk
MAX_NOGRAD_SAMPLES = 2**26


class Section(SettingsModel):
    """Base of every section with fixed keys (unknown keys refused, numbers finite)."""


AutoBool = Union[Literal["auto"], bool]
_NO_STEPS = "to skip this stage pick another one: stage=reconstruct | stylize | all | export"
_CHUNK_OFF = "there is no 'no chunking': a larger chunk renders more rays at once and needs more memory"


def _checkpoint_every(default: int) -> Any:
    return Setting(default, ge=1, le=10**9, description="steps between resume checkpoints (last.ckpt)",
                   off="checkpoints cannot be turned off (last.ckpt is what an interrupted run resumes from); a "
                       "larger value writes them less often", changes_results=False)


# ---------------------------------------------------------------------- the sections with fixed keys
class OccupancyConfig(Section):
    """``render.occupancy``: the occupancy grid for empty-space skipping."""

    enabled: AutoBool = Setting("auto", description="auto: on, except for forward-facing (NDC) captures without "
                                "weighted sampling (an SDF backbone there) | true | false")
    resolution: Int = Setting(64, ge=1, le=256, description="cells per side (shrunk to what the images resolve)",
                              off="render.occupancy.enabled=false turns the grid off")
    update_every: Int = Setting(16, ge=1, le=1_000_000, description="training steps between grid refreshes")
    threshold: Float = Setting(0.01, gt=0.0, le=1.0, description="opacity of a cell above which it counts as occupied",
                               off="render.occupancy.enabled=false turns the grid off")
    warmup_steps: Int = Setting(64, ge=0, le=10**9, description="steps during which every cell is re-evaluated")
    sampling: Literal["auto", "occupied", "weighted"] = Setting(
        "auto", description="where the grid puts a ray's samples: occupied (uniformly over the occupied cells) | "
        "weighted (density backbones: as dense as the cells' transmittance-weighted opacities, a proposal that "
        "crowds them at the first surface) | auto: weighted for a density backbone on a forward-facing (NDC) "
        "capture, whose frustum is nearly all occupied, occupied otherwise (README, BENCHMARKS.md fern)",
        off="render.occupancy.enabled=false turns the grid off")
    weighted_samples: Optional[Int] = Setting(16, ge=1, le=1024, description="samples per ray while training "
                                              "where the grid places them by weight (sampling=weighted): crowded "
                                              "where rays end, fewer suffice and each step is cheaper (README); "
                                              "null: render.num_samples",
                                              off="render.occupancy.sampling=occupied")
    uniform_share: Fraction = Setting(0.2, description="weighted sampling: share of each ray's samples spread "
                                      "uniformly over the occupied cells it crosses (so surfaces the grid "
                                      "underrates still get gradient)",
                                      off="render.occupancy.sampling=occupied")


class RenderConfig(Section):
    """``render``: ray sampling and compositing, shared by every stage."""

    num_samples: Int = Setting(32, ge=1, le=1024, description="samples per ray")
    sdf_color_normal: bool = Setting(False, description="SDF backbones: normals into the colour net (the papers: true)")
    sdf_grad_samples: Fraction = Setting(0.125, description="SDF backbones: fraction of samples whose gradient "
                                         "(eikonal) is computed while training",
                                         off="reconstruct.lambda_eikonal=0 turns the eikonal term off")
    neus_alpha_mode: Literal["gradient", "sections"] = Setting("sections", description="NeuS opacity estimate")
    chunk: Int = Setting(4096, ge=1, le=2**20, description="rays per chunk of no-grad full-view rendering "
                         "(validation, evaluation, export renders; memory only)", off=_CHUNK_OFF,
                         changes_results=False)
    view_samples: Optional[Int] = Setting(24, ge=1, le=1024, description="samples per ray of full views rendered "
                                          "without grad (validation, evaluation, videos, stage=render) where an "
                                          "occupancy grid places them; null, or a scene without a grid (NDC "
                                          "captures): render.num_samples", changes_results=False)
    stop_transmittance: Float = Setting(1e-4, ge=0.0, le=0.1, description="no-grad renders (evaluation, videos, "
                                        "the stylization's first pass) stop marching a ray once its transmittance "
                                        "is below this, so each pixel changes by less than it; 0: every sample",
                                        changes_results=False)
    background_color: Optional[Color] = Setting([1.0, 1.0, 1.0], description="[r, g, b] in [0, 1] behind the field "
                                                "when no background model is used; null: no compositing")
    background_model: AutoBool = Setting("auto", description="learned environment map: auto (unbounded captures "
                                         "without masks) | true | false")
    ndc_bound: Float = Setting(1.5, gt=0.0, le=100.0, description="half side of the field box of forward-facing "
                               "(NDC) captures: NDC x, y of off-centre cameras reach ~1.45 (fern: 1.44)")
    occupancy: OccupancyConfig = Field(default_factory=OccupancyConfig)
    # ---- stage=render: videos of a finished run (none of these change a trained result)
    run: Optional[PathText] = Setting(None, description="stage=render: the run folder (or a checkpoint in it) to "
                                      "render; null: this config's stylization (with a prompt) or reconstruction",
                                      changes_results=False)
    path: str = Setting("orbit", min_length=1, description="stage=render camera path: orbit (around the capture) | "
                        "spiral (forward-facing, LLFF's) | training (the training cameras in order) | a nerfstudio "
                        "camera_path.json file", allowed="orbit, spiral, training or the path of a camera_path.json",
                        changes_results=False)
    path_frame: Literal["world", "normalized"] = Setting(
        "world", description="frame of a camera_path.json's cameras: world (the capture's own, as the exported "
        "meshes and cameras.json) | normalized (the training frame)", changes_results=False)
    frames: Int = Setting(120, ge=1, le=100_000, description="frames of an orbit / spiral (a file or training: "
                          "their own cameras)", changes_results=False)
    resolution: Union[Literal["auto"], Annotated[Int, Field(ge=8, le=8192)]] = Setting(
        "auto", description="long side of the rendered frames in pixels; auto: the run's own (a stylization's "
        "stylize.resolution, a reconstruction's image size; a camera_path.json's render size)",
        allowed="auto or an integer in [8, 8192]", changes_results=False)
    fps: Optional[Int] = Setting(None, ge=1, le=240, description="frames per second of the video; null: the "
                                 "camera_path.json's, else 24", changes_results=False)
    channels: Annotated[list[Literal["rgb", "depth", "normal", "opacity", "side"]], Field(min_length=1)] = Setting(
        ["rgb"], description="videos to write: rgb | depth (turbo colour map, one range for the whole path) | "
        "normal | opacity | side (source | stylized, stylization runs)", changes_results=False)
    png: bool = Setting(False, description="also write each channel as a PNG sequence", changes_results=False)


class ReconstructConfig(Section):
    """``reconstruct``: stage 1, fitting the field to the photos."""

    steps: Int = Setting(4000, ge=1, le=10**9, description="optimizer steps", off=_NO_STEPS)
    batch_rays: Int = Setting(512, ge=1, le=2**18, description="random training rays per step")
    lr: Float = Setting(0.01, gt=0.0, le=10.0, description="Adam rate of the encoding (grid) parameters")
    lr_mlp: Float = Setting(0.003, gt=0.0, le=10.0, description="Adam rate of the MLPs (times encoding.mlp_lr_scale)")
    lr_final: Fraction = Setting(0.1, description="both rates decay exponentially to this fraction of their "
                                 "initial value over reconstruct.steps")
    lambda_rgb: Float = Setting(1.0, gt=0.0, le=1e6, description="weight of the photo loss (Eq. 2); it is what "
                                "reconstructs the scene, so it cannot be 0")
    lambda_eikonal: Float = Setting(0.1, ge=0.0, le=1e6, description="weight of the eikonal term (SDF); 0: off")
    lambda_mask: Float = Setting(0.1, ge=0.0, le=1e6, description="weight of the mask BCE (scenes with mattes); 0: off")
    mask_ray_share: Union[Literal["auto"], Annotated[Float, Field(ge=0.0, le=1.0)]] = Setting(
        "auto", description="scenes with mattes: share of each step's rays drawn from inside the mattes (the rest "
        "from all pixels) once reconstruct.mask_ray_share_after steps have passed; auto: 0.8 where the mattes cover "
        "less than half of the training pixels (a subject that fills a minority of the frame gets most of the "
        "batch), else 0 (the scene setup decides and logs why); 0: all rays uniform over the pixels",
        allowed="auto or a number in [0, 1]")
    mask_ray_share_after: Int = Setting(2000, ge=0, le=10**9, description="steps of rays drawn uniformly over all "
                                        "pixels before reconstruct.mask_ray_share applies: the background is carved "
                                        "out first (from step 0, short runs keep floaters near the box corners)")
    val_every: Int = Setting(1000, ge=0, le=10**9, description="steps between validations; 0: no validation",
                             changes_results=False)
    checkpoint_every: Int = _checkpoint_every(100)
    val_views: Int = Setting(2, ge=0, le=100_000, description="held-out views rendered at validation; 0: all",
                             changes_results=False)


class StylizeConfig(Section):
    """``stylize``: stage 2, the text-driven fine-tuning (Eq. 8)."""

    steps: Int = Setting(130, ge=1, le=10**9, description="optimizer steps (one view each)", off=_NO_STEPS)
    epochs: Optional[Int] = Setting(None, ge=1, le=10**6, description="if set, steps = epochs x training views "
                                    "(the paper: 4); null: use steps")
    lr: Float = Setting(0.01, gt=0.0, le=10.0, description="Adam rate of the encoding (grid) parameters")
    lr_mlp: Float = Setting(0.0025, gt=0.0, le=10.0, description="Adam rate of the MLPs")
    resolution: Union[Literal["auto"], Annotated[Int, Field(ge=8, le=4096)]] = Setting(
        "auto", description="long side (pixels) of the view the CLIP losses see; auto: the loaded "
        "images' own (the data resolution policy: 270x480 selfies, 256x256 H3DS head, as the paper)",
        allowed="auto or an integer in [8, 4096]")
    patch_size: Int = Setting(64, ge=1, le=1024, description="side of the patches re-rendered with grad (Sec. 4.4)",
                              off="stylize.backprop=retain renders the view once with grad, without patches")
    backprop: Literal["patch", "retain"] = Setting(
        "patch", description="how the image losses' gradient reaches the field (Sec. 4.4): patch (the paper's: the "
        "view rendered without grad, then re-rendered patch by patch with grad; memory bounded by "
        "stylize.patch_size) | retain (the view rendered once with grad and its graph kept until the backward: "
        "the re-render is saved, the memory holds every evaluated sample of the view; the same gradient to "
        "float rounding)")
    num_samples: Optional[Int] = Setting(16, ge=1, le=1024, description="samples per ray while stylizing, where an "
                                         "occupancy grid places them at the surface; null, or a scene without a "
                                         "grid (NDC captures): render.num_samples")
    chunk: Int = Setting(8192, ge=1, le=2**20, description="rays per chunk of the no-grad first pass (Sec. 4.4); "
                         "the random sample offsets are drawn per chunk, so it is part of the cache key",
                         off=_CHUNK_OFF)
    freeze_geometry: bool = Setting(False, description="keep the shape, stylize the colour only")
    num_negatives: Int = Setting(64, ge=1, le=100_000, description="negative prompts per step (Eq. 5)",
                                 off="experiment.lambda_global=0 experiment.lambda_local=0 turn the contrastive "
                                     "terms off (or experiment=no_contrastive)")
    negatives: str = Setting("auto", min_length=1, description="negative prompts (Eq. 5): auto | package | "
                             "official | /path/to/file.txt")
    negative_threshold: Union[Literal["auto"], Annotated[Float, Field(ge=-1.0, le=1.0)]] = Setting(
        "auto", description="negatives whose text cosine to the target exceeds this are excluded "
        "(besides the rules by meaning); auto: the guidance's (CLIP 0.85, imagenet 0.2)",
        allowed="auto or a cosine in [-1, 1]")
    tau: Float = Setting(0.07, gt=0.0, le=100.0, description="temperature of the contrastive losses (Eq. 5)",
                         off="experiment.lambda_global=0 experiment.lambda_local=0 turn the contrastive terms off")
    local_patches: Int = Setting(4, ge=0, le=1024, description="local patches per step (Eq. 6); 0: no local term")
    local_patch_frac: Fraction = Setting(0.1, description="local patch AREA as a fraction of the view's area",
                                         off="stylize.local_patches=0 or experiment.lambda_local=0 turns the local "
                                             "term off")
    render_every: Int = Setting(25, ge=0, le=10**9, description="steps between saved source|stylized renders; 0: none",
                                changes_results=False)
    checkpoint_every: Int = _checkpoint_every(10)
    video_frames: Int = Setting(24, ge=0, le=100_000, description="frames of the orbit video; 0: no video",
                                changes_results=False)
    video_fps: Int = Setting(12, ge=1, le=240, description="frames per second of the video",
                             off="stylize.video_frames=0 turns the video off", changes_results=False)
    occupancy_update_every: Int = Setting(8, ge=0, le=10**9, description="steps between re-estimates of the "
                                          "occupancy grid from the stylized field; 0: keep the reconstruction's")
    occupancy_band: Float = Setting(3.0, gt=0.0, le=1000.0, description="SDF band (occupancy cells) around the "
                                    "moving surface that is sampled")


MeshFormat = Literal["ply", "obj", "glb"]


class ExportConfig(Section):
    """``export``: meshes by marching cubes, and (``stage=export``) Gaussian splats."""

    enabled: bool = Setting(True, description="write meshes (source, stylized, displacement)")
    resolution: Int = Setting(128, ge=8, le=1024, description="marching-cubes grid cells per side",
                              off="export.enabled=false turns mesh export off")
    level: Optional[Float] = Setting(None, description="iso-level; null: the backbone's (0 for SDF, "
                                     "backbone.mesh_level for nerf)")
    chunk: Int = Setting(65536, ge=1, le=2**24, description="points per field call (memory only)", off=_CHUNK_OFF,
                         changes_results=False)
    remove_floaters: bool = Setting(True, description="drop small disconnected components")
    formats: Annotated[list[MeshFormat], Field(min_length=1)] = Setting(
        ["ply"], description="mesh files to write", off="export.enabled=false turns mesh export off")
    frame: Literal["world", "normalized"] = Setting(
        "world", description="coordinates of the written meshes: world (the capture's own frame, the "
        "normalization undone; NDC captures converted) or normalized (the training frame); the file says which")
    texture: bool = Setting(True, description="also write <mesh>_textured.obj/.mtl/.png and .glb: a UV atlas "
                            "(xatlas) with the field's colour baked into a texture, for Blender and co.")
    texture_size: Int = Setting(1024, ge=64, le=8192, description="side (pixels) of the baked texture",
                                off="export.texture=false writes no textured meshes")
    texture_faces: Int = Setting(20000, ge=0, le=10**8, description="triangles of the textured copy: the mesh is "
                                 "decimated to this many before its UV unwrap (the texture carries the colour "
                                 "detail; the plain mesh files keep every triangle); 0: no decimation")
    splats: bool = Setting(False, description="stage=export: also fit the field as 3D Gaussian splats and write "
                           "them as a 3DGS .ply (splats/<name>.ply, export.frame's frame) that splat viewers open")
    splat_count: Int = Setting(10000, ge=100, le=10**7, description="Gaussians of the splat export",
                               off="export.splats=false writes no splats")
    splat_steps: Int = Setting(500, ge=0, le=10**6, description="optimizer steps fitting the splats to the field's "
                               "renders (0: the surface initialization as it is)")
    splat_resolution: Int = Setting(128, ge=16, le=2048, description="long side (pixels) of the field's renders the "
                                    "splats are fitted to")


LoggerName = Literal["tensorboard", "csv", "wandb"]


class LoggerConfig(Section):
    """``logger`` (group ``conf/logger``): where the training curves and periodic renders go."""

    name: LoggerName = Setting("tensorboard", description="tensorboard (events under <run>/tb: losses, PSNR, "
                               "render pairs as images) | csv | wandb (needs the wandb package)",
                               changes_results=False)
    csv: bool = Setting(True, description="also keep <run>/logs/version_N/metrics.csv", changes_results=False)
    project: str = Setting("nerfart_plugin", min_length=1, description="W&B project", changes_results=False)
    entity: Optional[str] = Setting(None, description="W&B entity; null: the user's default",
                                    changes_results=False)
    mode: Literal["online", "offline", "disabled"] = Setting("online", description="W&B mode (WANDB_MODE wins)",
                                                             changes_results=False)


class ViewerConfig(Section):
    """``viewer``: the live web viewer on a training run (``python -m nerfart_plugin.viewer RUN`` views a finished
    one). It only watches: none of these settings changes what is computed."""

    live: bool = Setting(False, description="serve the viewer while the run trains (a URL is logged): the field "
                         "from the browser's camera, pause / resume / stop-and-save", changes_results=False)
    host: str = Setting("127.0.0.1", min_length=1, description="address to bind; 0.0.0.0 serves every network "
                        "interface (anyone who can reach the machine can watch)", changes_results=False)
    port: Int = Setting(8080, ge=0, le=65535, description="port (the next free one if taken; 0: any free port)",
                        changes_results=False)
    render_share: Float = Setting(0.1, gt=0.0, le=1.0, description="the most of the wall time the viewer's frames "
                                  "may take while training (1: no cap)", changes_results=False)


Precision = Literal["32-true", "32", 32, "16-mixed", "16", 16, "bf16-mixed", "bf16", "16-true", "bf16-true",
                    "64-true", "64", 64]
Devices = Union[Literal["auto", -1], Annotated[Int, Field(ge=1, le=4096)],
                Annotated[list[Annotated[Int, Field(ge=0, le=4096)]], Field(min_length=1)]]


class TrainerConfig(Section):
    """``trainer``: Lightning Trainer options."""

    log_every_n_steps: Int = Setting(10, ge=1, le=10**9, description="steps between logged metrics",
                                     changes_results=False)
    precision: Precision = Setting("32-true", description="Lightning precision: 32-true, or bf16-mixed / 16-mixed "
                                   "(colour and NeRF density nets under autocast; SDF geometry, rays and occupancy "
                                   "lookups stay float32; no faster on a 2-core CPU, README 'Speed knobs')")
    strategy: str = Setting("auto", min_length=1, description="Lightning strategy: auto (one device) | ddp | ...",
                            allowed="a Lightning strategy: auto, ddp, ddp_spawn, fsdp, deepspeed, ... "
                                    "(lightning.pytorch.strategies.StrategyRegistry)")
    devices: Devices = Setting(1, description="devices per node: N | auto | -1 (all) | [ids]",
                               off="device=cpu runs on the CPU")
    num_nodes: Int = Setting(1, ge=1, le=100_000, description="nodes for multi-node DDP")

    @field_validator("strategy")
    @classmethod
    def _lightning_strategy(cls, value: str) -> str:
        if value.lower() == "auto":
            return value
        from lightning.pytorch.strategies import StrategyRegistry

        if value.lower() not in StrategyRegistry.available_strategies():
            raise ValueError(f"unknown Lightning strategy {value!r}")
        return value


class ExperimentConfig(Section):
    """``experiment``: the weights of Eq. 8 (``experiment=full``: these defaults) and of the extra terms; 0 turns a
    term off (each is a ``lambda_<name>`` of a loss table in :mod:`nerfart_plugin.systems`)."""

    name: str = Setting("full", min_length=1, description="name of the experiment (for the records)",
                        changes_results=False)
    directional: Literal["relative", "absolute"] = Setting("relative", description="Eq. 4 (relative, NeRF-Art) or "
                                                           "Eq. 3 (absolute, CLIP-NeRF style)")
    lambda_dir: Float = Setting(1.0, ge=0.0, le=1e4, description="weight of the directional CLIP loss; 0: off")
    lambda_global: Float = Setting(0.2, ge=0.0, le=1e4, description="weight of the global contrastive loss; 0: off")
    lambda_local: Float = Setting(0.1, ge=0.0, le=1e4, description="weight of the local contrastive loss; 0: off")
    lambda_perceptual: Float = Setting(2.0, ge=0.0, le=1e4, description="weight of the VGG perceptual loss; 0: off")
    lambda_reg: Float = Setting(0.1, ge=0.0, le=1e4, description="weight of the weight regularization; 0: off")
    lambda_eikonal: Float = Setting(0.1, ge=0.0, le=1e4, description="not in Eq. 8: eikonal weight while "
                                    "stylizing SDF backbones; 0: off")
    lambda_silhouette: Float = Setting(0.0, ge=0.0, le=1e4, description="not in Eq. 8: keep the source render's "
                                       "silhouette (opacity BCE); 0: off (the paper)")


def _prompt_text(value: Any) -> Any:
    """A prompt is text: ``+prompt=1984`` reaches here as the int 1984 from Hydra's parser."""
    return str(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else value


PromptText = Annotated[str, BeforeValidator(_prompt_text), Field(min_length=1)]


MixWeight = Annotated[Float, Field(ge=-1.0, le=2.0)]


class PreviewConfig(Section):
    """``preview``: ``stage=preview``, a short, small version of the stylization a full run would make (its
    losses, learning rates, views and seeds; fewer steps, a smaller size, the subject's outline held), with a
    verdict on the prompt in words."""

    steps: Int = Setting(40, ge=1, le=10_000, description="optimizer steps of the preview (one view each), with "
                         "the full run's losses, learning rates, views and seeds")
    resolution: Union[Literal["auto"], Annotated[Int, Field(ge=16, le=1024)]] = Setting(
        "auto", description="long side (pixels) of the preview's views; auto: 128, or the full run's "
        "(stylize.resolution) where that is smaller")
    strength: Float = Setting(1.0, ge=0.0, le=2.0, description="the strength the preview's views are shown at "
                              "(the dial, applied to the preview's change): > 1 pushes the change on")
    lambda_silhouette: Float = Setting(5.0, ge=0.0, le=1e4, description="weight of the silhouette term in the "
                                       "preview's steps (experiment.lambda_silhouette, the larger of the two): "
                                       "holds the subject's outline, which the full run keeps and a short run "
                                       "without it loses; 0: the full run's losses only")


class MixConfig(Section):
    """``mix``: stage=render / stage=export of several stylizations of one source, combined without retraining:
    θ_src + Σ_i w_i (θ_i − θ_src) (:mod:`nerfart_plugin.results.blend`). Outputs go into the first run's folder, named
    ``-mix<weights>-<hash of the runs>``."""

    runs: list[PathText] = Setting([], description="stylization run folders of ONE reconstruction to combine "
                                   "([]: no mix)", changes_results=False)
    weights: list[MixWeight] = Setting([], description="one weight per run, each in [-1, 2] (0: leave that style "
                                       "out, 1: all of it)", changes_results=False)


def _file_shorthand(value: Any) -> Any:
    """``region=<file>`` / ``style_image=<file>``: a file alone, the shorthand of ``<section>.file=<file>``."""
    return {"file": value} if isinstance(value, (str, Path)) else value


Six = Annotated[list[Float], Field(min_length=6, max_length=6)]
Three = Annotated[list[Float], Field(min_length=3, max_length=3)]


class RegionConfig(Section):
    """``region``: stylize, render and export only a part of the scene (``nerfart_plugin.api.Region``). The shapes
    are in the capture's world frame (the exported meshes' and the viewer's); given together they are united,
    then ``invert`` keeps the rest. ``region=<file>`` is ``region.file=<file>``."""

    file: Optional[PathText] = Setting(None, description="a region file (region.npz: Region.save, the viewer's "
                                       "Regions panel)")
    box: Optional[Six] = Setting(None, description="a box [cx, cy, cz, hx, hy, hz]: centre and half sizes (world "
                                 "units)")
    ellipsoid: Optional[Six] = Setting(None, description="an ellipsoid [cx, cy, cz, rx, ry, rz]: centre and radii "
                                       "(world units)")
    rotation: Optional[Three] = Setting(None, description="the box's and ellipsoid's rotation, Euler angles in "
                                        "degrees about x, then y, then z; null: none")
    feather: Optional[Float] = Setting(None, ge=0.0, le=1e6, description="width of a shape's soft edge, outward "
                                       "(world units); null: two cells of the region's grid")
    margin: Optional[Float] = Setting(None, ge=0.0, le=1e6, description="how far the stylized geometry may grow "
                                      "past the region (world units); null: the feather")
    invert: bool = Setting(False, description="everywhere but the region")
    resolution: Int = Setting(96, ge=8, le=256, description="cells a side of the grid the region is sampled on over "
                              "the field box")

    @property
    def given(self) -> bool:
        """A region is asked for (a file or a shape)."""
        return any(v is not None for v in (self.file, self.box, self.ellipsoid))


class StyleImageConfig(Section):
    """``style_image``: a picture whose style the stylization follows, alone or beside ``prompt`` (ARF's
    nearest-neighbour feature matching, :mod:`nerfart_plugin.guidance.style_image`). ``+style_image=<file>`` is
    ``style_image.file=<file>``. The features are the perceptual network's (``guidance.perceptual``: VGG16 with
    ``guidance=clip``, EfficientNet-Lite0 with ``guidance=imagenet``) at ``layers``."""

    file: Optional[PathText] = Setting(None, description="a PNG or JPEG whose style to follow (any size; 16-bit, "
                                       "grayscale and RGBA are read; transparency shows white); runs are keyed by "
                                       "its content, not its path", changes_results=False)
    lambda_style: Float = Setting(10.0, ge=0.0, le=1e4, description="weight of the nearest-neighbour feature "
                                  "matching to the picture (ARF's NNFM); 0: off")
    lambda_palette: Float = Setting(1.0, ge=0.0, le=1e4, description="weight of the pull of the colours toward the "
                                    "source views recoloured to the picture's palette (histogram matching); 0: off")
    layers: Union[Literal["auto"], list[str]] = Setting("auto", description="the feature layers matched: VGG16 "
                                                        "names (relu3_1, ...) or EfficientNet-Lite blocks (block1, "
                                                        "...); auto: VGG16 relu3_1, relu3_2, relu3_3 (ARF's), Lite0 "
                                                        "block1, block2")
    size: Int = Setting(256, ge=32, le=2048, description="long side (pixels) the picture is resized to before its "
                        "features and palette are taken")

    @property
    def given(self) -> bool:
        """A picture is asked for."""
        return self.file is not None


def Component(key: str) -> Any:
    """The annotation of the component section ``key``: its component's typed Config, picked by ``name``."""
    return Annotated[SerializeAsAny[ComponentConfig], BeforeValidator(lambda v: typed_section(key, v))]


def _given_json(section: BaseModel) -> dict:
    """A typed component section as plain data, the settings it was given only (nested sections too)."""
    return section.model_dump(mode="json", exclude_unset=True)


class RunConfig(Section):
    """The top-level keys of a run's config, with the sections as nested models."""

    stage: Literal["reconstruct", "stylize", "all", "export", "render", "preview"] = Setting(
        "all", description="which stages to run (preview: a short low-resolution stylization, preview.*)",
        changes_results=False)
    prompt: Optional[PromptText] = Setting(None, description="the style text; stylize/all/preview need it or a "
                                           "style_image")
    source_prompt: PromptText = Setting("auto", description="source text of the directional loss; auto: from "
                                        "the capture type")
    prompt_augment: bool = Setting(True, description="expand known painter/style names to the paper's prompts")
    seed: Seed = Setting(0, description="seed of every random choice")
    device: str = Setting("auto", pattern=r"^(auto|cpu|mps|cuda(:\d+)?)$", description="the compute device: auto "
                          "(CUDA, then MPS, then CPU) | cpu | cuda | cuda:N | mps; a reconstruction made on one "
                          "device is reused on another", allowed="one of auto, cpu, cuda, cuda:N (N = 0, 1, ...), mps",
                          changes_results=False)
    output_root: PathText = Setting("outputs", description="where runs, caches and Hydra logs go",
                                    changes_results=False)
    resume: bool = Setting(True, description="resume an interrupted run; false: start over (the old folder is kept)",
                           changes_results=False)
    source_checkpoint: Optional[PathText] = Setting(None, description="a reconstruction checkpoint to stylize/export "
                                                    "(null: the cached reconstruction of these settings)")
    objective: str = Setting("auto", pattern=r"^[A-Za-z_][\w.]*$", description="metric a sweep maximizes: auto "
                             "(stylization.clip_directional_similarity, else reconstruction.psnr) or a results key",
                             allowed="auto or a dotted results key such as stylization.clip_score",
                             changes_results=False)
    compile: Literal["auto", "on", "off"] = Setting(
        "auto", description="evaluate the fields through torch.compile (kernels cached on disk across runs): on | "
        "off | auto (on where a compiler is available and the work pays for the compile: reconstructions of 2000 "
        "steps or more, stylizations of 50 or more, videos of 60 frames or more, the web viewer; shorter work on a "
        "CPU still takes the grid's fused lookup kernel); off: PyTorch's own kernels only; results equal to float "
        "rounding", changes_results=False)
    lock_timeout: Optional[Float] = Setting(None, ge=0.0, le=1e7, description="seconds to wait for a run folder "
                                            "that another process holds; 0: stop at once; null: wait until it ends",
                                            changes_results=False)
    strength: Float = Setting(1.0, ge=0.0, le=2.0, description="stage=render / stage=export of a stylization: "
                              "the style's strength without retraining (0: the source, 1: as trained, 2: twice its "
                              "change; outputs named -s<strength>)", changes_results=False)
    mix: MixConfig = Field(default_factory=MixConfig)
    region: Annotated[RegionConfig, BeforeValidator(_file_shorthand)] = Field(default_factory=RegionConfig)
    style_image: Annotated[StyleImageConfig, BeforeValidator(_file_shorthand)] = Field(
        default_factory=StyleImageConfig)
    preview: PreviewConfig = Field(default_factory=PreviewConfig)
    viewer: ViewerConfig = Field(default_factory=ViewerConfig)
    render: RenderConfig = Field(default_factory=RenderConfig)
    reconstruct: ReconstructConfig = Field(default_factory=ReconstructConfig)
    stylize: StylizeConfig = Field(default_factory=StylizeConfig)
    export: ExportConfig = Field(default_factory=ExportConfig)
    trainer: TrainerConfig = Field(default_factory=TrainerConfig)
    experiment: ExperimentConfig = Field(default_factory=ExperimentConfig)
    logger: LoggerConfig = Field(default_factory=LoggerConfig)
    # component sections: each typed as the Config of the component its ``name`` picks (config.sections)
    data: Component("data") = Field(default_factory=lambda: {"name": "h3ds"}, validate_default=True)
    backbone: Component("backbone") = Field(default_factory=lambda: {"name": "volsdf"}, validate_default=True)
    encoding: Component("encoding") = Field(default_factory=lambda: {"name": "grid"}, validate_default=True)
    guidance: Component("guidance") = Field(default_factory=lambda: {"name": "clip"}, validate_default=True)
    #: the validated settings as given (what ``config.yaml`` records and the cache keys hash), set by parse_config
    _plain: Optional[dict] = PrivateAttr(default=None)

    @property
    def plain(self) -> dict:
        """The settings as given and validated (:func:`parse_config`): what a run folder's ``config.yaml``
        records and the cache keys hash (the component sections with only the keys that were set)."""
        if self._plain is None:
            self._plain = {**self.model_dump(mode="json", exclude=set(TOP_LEVEL)),
                           **{k: _given_json(getattr(self, k)) for k in TOP_LEVEL}}
        return self._plain



#: section name -> model, for the sections with fixed keys
SECTIONS: dict[str, type[Section]] = {
    "render": RenderConfig, "reconstruct": ReconstructConfig, "stylize": StylizeConfig, "export": ExportConfig,
    "trainer": TrainerConfig, "experiment": ExperimentConfig, "logger": LoggerConfig, "mix": MixConfig,
    "preview": PreviewConfig, "viewer": ViewerConfig, "region": RegionConfig,
}
