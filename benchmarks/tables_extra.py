"""The generated tables made from the code and the committed files rather than docs/results (`benchmarks.tables`
writes them): docs/method.md's table of the two methods, from `matspray.presets` (the table the code reads): every
setting where `--method matspray` differs from `--method paper`, with the paper's value and its source, and the
settings where the text is silent and both take the released code's value; docs/benchmarks.md's table of the real
objects, measured on their files."""

from __future__ import annotations

from benchmarks.tables_files import grouped
from matspray.presets import ADDITIONS, RELEASED_VALUES


def resolved(config, path: str):
    """The value of the dotted setting `path` in a (nested) frozen config."""
    for name in path.split("."):
        config = getattr(config, name)
    return config


def shown(value) -> str:
    return f"`{value}`" if value is not None else "none"


def table_methods(results=None) -> str:
    """`| addition | setting | matspray (demo) | paper | the paper's value from |`, then the released code's values."""
    from matspray.method.config import build_config  # torch: only when this table is made

    ours, paper = build_config("demo"), build_config("demo", "paper")
    lines = [
        "| addition | what `matspray` does | setting | matspray (demo) | paper | the paper's value from |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for a in ADDITIONS:
        cells = (f"`{a.name}`", a.what, f"`{a.setting}`", shown(resolved(ours, a.setting)))
        lines.append("| " + " | ".join((*cells, shown(resolved(paper, a.setting)), a.source)) + " |")
    lines += ["", "Where the text is silent, both methods take the released code's value:", ""]
    lines += ["| setting | both methods | from |", "| --- | --- | --- |"]
    lines += [f"| `{path}` | {shown(value)} | {source} |" for path, value, source in RELEASED_VALUES]
    return "\n".join(lines)


def table_real_objects(results=None) -> str:
    """docs/benchmarks.md's table of the real objects, measured on the committed files (`benchmarks.real_objects`)."""
    from benchmarks.real_objects import METAL_AREA, SETS, parts_metal_share, set_files, split
    from matspray.gltf import read_gltf
    from matspray.synth.gltf_object import asset_parts

    lines = [
        "| set | object | licence | triangles | textures | metal share | kind | file |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    total = 0
    for which in SETS:
        for spec, path in zip(split()[which], set_files(which)):
            parts, textures, _ = asset_parts(read_gltf(path))
            triangles = sum(len(part.faces) for part in parts)
            side = max(max(t.base_color.shape[:2] + t.metallic.shape[:2]) for t in textures)  # largest
            size = path.stat().st_size
            total += size
            share = parts_metal_share(parts, textures)  # the file read once
            cells = (f"`{which}`", spec.name, spec.licence, grouped(triangles))
            cells += (
                f"{side} px",
                f"{share:.2f}",
                spec.kind,
                f"{grouped(size // 1000)} kB",
            )
            lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        f"In all {total / 2**20:.1f} MiB. Metal share: the part of the surface whose metallic is above 0.5; "
        f'an object is "metal" from a share of {METAL_AREA:.2f}.',
    ]
    return "\n".join(lines)


PRESET_PURPOSES = {  # what each preset is for: docs text, beside the sizes the code holds
    "test": "a quick check that everything runs",
    "demo": "(default) a real capture on a 2-core CPU, in minutes",
    "quality": "sharper, for a longer run and more memory",
    "paper": "the paper's settings, on a GPU ([gpu.md](gpu.md))",
}


def table_presets(results=None) -> str:
    """docs/guide/your-photos.md's table of the presets, each one's sizes resolved from `matspray.presets`."""
    from matspray.method.config import build_config  # torch: only when this table is made
    from matspray.presets import PRESETS, WORKING_SIZE

    lines = [
        "| `--preset` | for | photos' longest side | Gaussian Splatting trains at | its steps | Gaussians at most "
        "| refinement steps |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for preset in PRESETS:
        config = build_config(preset)
        geometry = config.geometry
        cells = (f"`{preset}`", PRESET_PURPOSES[preset], f"{WORKING_SIZE[preset]} px", f"{geometry.resolution} px")
        cells += tuple(grouped(n) for n in (geometry.iterations, geometry.max_gaussians, config.refine.iterations))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


EXTRA = {  # the tables `benchmarks.tables` makes from the code and the committed files rather than docs/results
    "methods": (table_methods, []),
    "real-objects": (table_real_objects, []),
    "presets": (table_presets, []),
}
