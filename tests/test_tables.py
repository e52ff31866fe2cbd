import math

from matspray.eval.tables import (
    ablation_table,
    format_metallic_psnr,
    material_table,
    softmax_table,
    tables_markdown,
    timings_table,
    write_tables,
)

OURS = {
    "relighting": {"psnr": 27.2821, "ssim": 0.8971, "lpips": 0.0804},
    "basecolor": {"psnr": 21.341, "ssim": 0.873, "lpips": 0.125},
    "roughness": {"psnr": 15.331, "ssim": 0.820, "lpips": 0.181},
    "metallic": {"psnr": 27.2024, "ssim": 0.893, "lpips": 0.106, "psnr_infinite": 9, "objects": 17},
}


def test_table1_single_method_matches_the_paper_layout():
    assert material_table({"Ours": OURS}) == "\n".join(
        [
            "| Task | PSNR ↑ | SSIM ↑ | LPIPS ↓ |",
            "| :--- | ---: | ---: | ---: |",
            "| Relighting | 27.282 | 0.897 | 0.080 |",
            "| BaseColor | 21.341 | 0.873 | 0.125 |",
            "| Roughness | 15.331 | 0.820 | 0.181 |",
            "| Metallic | ∞*/27.202 | 0.893 | 0.106 |",
        ]
    ) + (
        "\n\n\\* 9 of 17 objects are non-metallic and predicted all zero, so their metallic PSNR is infinite; "
        "they are left out of the average after the slash."
    )


def test_table1_missing_rows_unavailable_lpips_and_best_in_bold():
    other = {"relighting": {"psnr": 25.483, "ssim": 0.875, "lpips": None}, "roughness": {"psnr": 16.182}}
    lines = material_table({"Ours": OURS, "R3DGS": other}).splitlines()
    assert lines[0] == (
        "| Task | Ours PSNR ↑ | Ours SSIM ↑ | Ours LPIPS ↓ | R3DGS PSNR ↑ | R3DGS SSIM ↑ | R3DGS LPIPS ↓ |"
    )
    assert lines[2] == "| Relighting | **27.282** | **0.897** | 0.080 | 25.483 | 0.875 | n/a |"
    assert lines[3] == "| BaseColor | 21.341 | 0.873 | 0.125 | — | — | — |"
    assert lines[4] == "| Roughness | 15.331 | 0.820 | 0.181 | **16.182** | — | — |"
    assert lines[5] == "| Metallic | ∞*/27.202 | 0.893 | 0.106 | — | — | — |"
    assert lines[7].startswith("\\* Ours: 9 of 17 objects")


def test_table1_scale_aligned_rows_are_labelled():
    rows = {"relighting": {"psnr": 20.0}, "basecolor_aligned": {"psnr": 24.5, "ssim": 0.9, "lpips": 0.1}}
    text = material_table({"Ours": rows})
    assert "| BaseColor (scale-aligned) | 24.500 | 0.900 | 0.100 |" in text
    assert "Relighting (scale-aligned)" not in text
    assert "Scale-aligned rows: the prediction is multiplied per channel by the median ratio" in text


def test_metallic_cell_variants():
    assert format_metallic_psnr({"psnr": 30.0}) == "30.000"
    assert format_metallic_psnr({"psnr": 30.0, "psnr_infinite": 0}) == "30.000"
    assert format_metallic_psnr({"psnr": None, "psnr_infinite": 4}) == "∞*"
    assert format_metallic_psnr({"psnr": 12.3456, "psnr_infinite": 1}) == "∞*/12.346"
    assert format_metallic_psnr(None) == "—"


def test_ablation_tables_list_the_paper_variants_in_order():
    table2 = ablation_table(
        {
            "Proj. Average": {"psnr": 25.555, "ssim": 0.866, "lpips": 0.122},
            "Full": {"psnr": 29.164, "ssim": 0.9105, "lpips": 0.0626},
        }
    )
    assert table2.splitlines()[2:] == [
        "| Full | **29.164** | **0.910** | **0.063** |",
        "| Supervised | — | — | — |",
        "| Proj. Average | 25.555 | 0.866 | 0.122 |",
    ]
    softmax = softmax_table({"Without Softmax": {"psnr": 24.6, "ssim": 0.874, "lpips": None}, "Extra": {}})
    assert softmax.splitlines()[2:] == [
        "| Full | — | — | — |",
        "| Without Softmax | 24.600 | 0.874 | n/a |",
        "| Extra | — | — | — |",
    ]


def test_timings_table_sums_the_stages():
    table = timings_table(
        {"Ours": {"refine": 975.0, "predict": 112.0, "geometry": 131.0, "eval": 10.25}, "Other": {"geometry": 2490.0}}
    )
    assert table.splitlines() == [
        "| Stage | Ours (s) | Other (s) |",
        "| :--- | ---: | ---: |",
        "| Diffusion predictions | 112.0 | — |",
        "| Gaussian Splatting | 131.0 | 2490.0 |",
        "| Material optimization | 975.0 | — |",
        "| eval | 10.2 | — |",
        "| **Total** | **1228.2** | **2490.0** |",
    ]


def test_infinite_psnr_prints_as_infinity():
    assert "| Relighting | ∞ |" in material_table({"Ours": {"relighting": {"psnr": math.inf}}})


def test_document_has_every_section_and_says_what_is_missing(tmp_path):
    metrics = {
        "table1": {"Ours": OURS},
        "timings": {"Ours": {"predict": 1.0}},
        "lpips": "LPIPS unavailable: no weights file",
        "notes": ["Material predictions are simulated from ground truth."],
    }
    text = tables_markdown(metrics)
    assert text.startswith(
        "# MatSpray evaluation\n\n- Material predictions are simulated from ground truth.\n"
        "- LPIPS: LPIPS unavailable: no weights file\n"
    )
    assert "## Table 1: relighting and material maps\n\n| Task |" in text
    assert "## Table 2: ablation (Full / Supervised / Proj. Average)\n\n_No ablation runs._" in text
    assert "## Ablation: Neural Merger softmax\n\n_No softmax ablation runs._" in text
    assert "| **Total** | **1.0** |" in text
    path = write_tables(tmp_path / "eval" / "tables.md", metrics)
    assert path.read_text(encoding="utf-8") == text
    assert [p.name for p in path.parent.iterdir()] == ["tables.md"]  # no temporary file left behind
