"""`matspray export --run RUN --out FILE.glb`: the asset as a textured glTF 2.0 mesh; `--splats FILE.glb`: as
KHR_gaussian_splatting Gaussians with their materials; `--web DIR`: as a static page that relights it."""

import argparse
from pathlib import Path

from matspray.cli.options import VARIANT_HELP, add_compute_arguments, hidden_alias
from matspray.export.config import BAKES, ExportConfig
from matspray.web import DEFAULT_WEB_PSNR

DEFAULTS = ExportConfig()
OLD_NORMALS = {"mesh": 0.0, "asset": 1.0}  # --normals mesh|asset, the flag before --asset-normals


def old_normals(value: str) -> float:
    if value not in OLD_NORMALS:
        raise argparse.ArgumentTypeError(f"'{value}': choose mesh or asset, or pass --asset-normals SHARE")
    return OLD_NORMALS[value]


def web_psnr(value: str) -> float:
    """--web's DB: a PSNR above 0, or inf."""
    from matspray.errors import ConfigError

    try:
        decibels = float(value)
    except ValueError:
        decibels = float("nan")
    if not decibels > 0:
        raise ConfigError(f"--web DIR {value}: give the page's PSNR in dB, above 0 (inf draws every Gaussian)")
    return decibels


def add_splats_and_web_arguments(parser) -> None:
    """--splats and --web."""
    parser.add_argument(
        "--splats",
        nargs="+",
        metavar=("FILE.glb", "LIGHT"),
        help="the Gaussians as glTF with the KHR_gaussian_splatting extension, their colour baked under LIGHT (a name "
        "or .exr/.hdr file as relight's --env; default: the estimated light), with per-splat base colour, roughness, "
        "metallic and normal and the estimated light beside them, which MatSpray reads back (relight --run FILE.glb); "
        "FILE.spz: the baked splats alone, as SPZ",
    )
    parser.add_argument(
        "--web",
        nargs="+",
        metavar=("DIR", "DB"),
        help="a static page that relights the asset in the browser (open DIR/index.html, or put DIR on any host); it "
        "leaves out the Gaussians that add least per pixel they cover, as many as keeps its frames within DB of the "
        f"whole asset's (PSNR; default {DEFAULT_WEB_PSNR:g}), for browsers without a GPU; DB inf draws every "
        "Gaussian",
    )


def add_export_parser(parser) -> None:
    parser.description = (
        "Turn a run's Gaussian asset into a textured triangle mesh for engines and DCC tools: a closed surface "
        "from the asset's depth at the training cameras (TSDF + marching cubes), decimated to --faces, UV-unwrapped "
        "(xatlas), with baked base colour (sRGB) and metallic-roughness textures (G = roughness, B = metallic) and "
        "per-vertex normals, in one binary glTF 2.0 file. The estimated environment map is written beside it as "
        "FILE_envmap.exr and FILE_envmap.hdr (lat-long, Z-up; in Blender turn its vector 180 degrees about Z: "
        "docs/guide/export.md). --splats writes the Gaussians themselves (KHR_gaussian_splatting) and --web a page "
        "that relights them in a browser; any of the three may be given together."
    )
    parser.add_argument(
        "--run",
        type=Path,
        required=True,
        help="run folder made by `matspray run` (for --web and --splats also a .glb written by --splats)",
    )
    parser.add_argument("--out", type=Path, help="the mesh: the .glb file to write")
    add_splats_and_web_arguments(parser)
    parser.add_argument("--variant", help=VARIANT_HELP)
    parser.add_argument("--faces", type=int, help=f"face budget, >= 100 (default {DEFAULTS.faces})")
    parser.add_argument(
        "--texture-resolution",
        dest="texture_size",
        type=int,
        help=f"side of the square textures, a power of two in [64, 8192] (default {DEFAULTS.texture_size})",
    )
    parser.add_argument(
        "--frame",
        choices=("gltf", "dataset"),
        help="gltf: Y-up as glTF expects (default); dataset: the dataset's own Z-up world coordinates. "
        "The transform between the two is stored in the file's asset.extras.matspray",
    )
    parser.add_argument(
        "--grid",
        type=int,
        help=f"TSDF voxels along the object's longest side (default {DEFAULTS.grid}); finer surface, more time",
    )
    parser.add_argument(
        "--asset-normals",
        type=float,
        metavar="SHARE",
        help="share of the Gaussians' refined shading normals in the mesh's per-vertex normals, in [0, 1]: 0 keeps "
        f"the surface's own, 1 takes the Gaussians' alone (default {DEFAULTS.asset_normals})",
    )
    parser.add_argument(
        "--bake",
        choices=BAKES,
        help="where the textures read the materials: views (the asset's renders at the training views, what the "
        "Gaussians show), gaussians (the Gaussians around each texel, blended in 3D), auto (default: views for the "
        "assets made without 2D maps, gaussians for the others)",
    )
    parser.add_argument(
        "--silhouette-rounds",
        type=int,
        help=f"rounds that move the mesh's rim onto the asset's silhouettes in the training views "
        f"(default {DEFAULTS.silhouette_rounds}; 0: off)",
    )
    parser.add_argument(
        "--data",
        type=Path,
        help="the run's dataset, for the training cameras (default: the folder the run was made from)",
    )
    add_compute_arguments(parser)
    hidden_alias(parser, "--texture-size", "texture_size", type=int)  # the old name of --texture-resolution
    hidden_alias(parser, "--normals", "asset_normals", type=old_normals)


EXPORT_PACKAGES = ("trimesh", "xatlas", "skimage", "fast_simplification", "scipy", "pygltflib")  # the `export` extra
MESH_FLAGS = {  # flag -> its setting, read only for the mesh
    "--faces": "faces",
    "--texture-resolution": "texture_size",
    "--frame": "frame",
    "--grid": "grid",
    "--asset-normals": "asset_normals",
    "--bake": "bake",
    "--silhouette-rounds": "silhouette_rounds",
}


def mesh_config(args) -> ExportConfig:
    """The mesh's settings: the flags given, the defaults for the others."""
    chosen = {name: getattr(args, name) for name in MESH_FLAGS.values() if getattr(args, name, None) is not None}
    return ExportConfig(**chosen)


def export_main(args) -> int:
    from matspray.cli.options import refuse
    from matspray.errors import ConfigError, optional_module
    from matspray.files import check_output_file, check_output_folder

    if args.out is None and args.splats is None and args.web is None:
        raise ConfigError("say what to write: --out FILE.glb (a mesh), --splats FILE.glb or --web DIR")
    if args.out is None:
        refuse(
            [flag for flag, name in MESH_FLAGS.items() if getattr(args, name, None) is not None], "for --out FILE.glb"
        )
    if args.web is not None:
        if len(args.web) > 2:
            raise ConfigError(f"--web takes DIR and at most one DB, got {len(args.web)} values")
        args.web_psnr = web_psnr(args.web[1]) if len(args.web) == 2 else DEFAULT_WEB_PSNR
        args.web = check_output_folder(Path(args.web[0]), Path(args.web[0]))
    if args.splats is not None:
        if len(args.splats) > 2:
            raise ConfigError(f"--splats takes FILE.glb and at most one LIGHT, got {len(args.splats)} values")
        if Path(args.splats[0]).suffix.lower() not in (".glb", ".spz"):
            raise ConfigError(
                f"--splats writes a binary glTF (.glb) or an SPZ file (.spz): give one of those, not '{args.splats[0]}'"
            )
        check_output_file(Path(args.splats[0]), ".glb or .spz")
    if args.out is not None:
        for name in EXPORT_PACKAGES:  # before any work or torch: one line naming the extra, not an ImportError
            optional_module(name, "export", "matspray export")
    from matspray.device import out_of_memory_as_error
    from matspray.render.backend import compute_target

    device, backend = compute_target(args.device, args.backend)
    with out_of_memory_as_error("export", device):
        if args.out is not None:
            export_mesh(args, device, backend)
        if args.splats is not None or args.web is not None:
            from matspray.cli.splats import export_splats_and_web
            from matspray.render.backend import rendering_with

            with rendering_with(backend):  # the page's choice of Gaussians renders the asset (web.detail)
                for path in export_splats_and_web(args, device):
                    print(f"wrote {path}")
    return 0


def export_mesh(args, device, backend) -> None:
    from matspray.export.export import export_run
    from matspray.rundir import RunDir

    report = export_run(
        args.run,
        args.out,
        variant=args.variant or RunDir(args.run).require().default_variant(),
        config=mesh_config(args),
        data=args.data,
        device=device,
        backend=backend,
    )
    seconds = ", ".join(f"{name} {value:.1f} s" for name, value in report.seconds.items())
    print(
        f"wrote {report.files[0]}: {report.faces} faces, {report.vertices} vertices, "
        f"{report.texture_size}x{report.texture_size} textures ({seconds})"
    )
    for path in report.files[1:]:
        print(f"wrote {path}")
