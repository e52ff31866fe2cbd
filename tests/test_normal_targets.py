"""benchmarks.normal_targets: its refusals (the refinement it runs is the pipeline's, tested there)."""

import pytest

from benchmarks.normal_targets import main, parse_args


def test_weights_must_be_positive(capsys):
    with pytest.raises(SystemExit):
        parse_args(["--weights", "0"])
    assert "--weights: every weight must be > 0" in capsys.readouterr().err


def test_without_the_protocols_runs_it_says_which_command_to_run_first(tmp_path, capsys):
    pytest.importorskip("mitsuba")  # the object set draws its lights from the HDRIs the protocol uses
    from matspray.render.shade.lights import hdri_files

    if not hdri_files():
        pytest.skip("no HDR maps (../shared/data/hdri) to draw the protocol's objects from")
    (tmp_path / "objects" / "dev-00-seed1000" / "data").mkdir(parents=True)
    assert main(["--objects", "1", "--preset", "test", "--out", str(tmp_path)]) == 2
    assert "python -m benchmarks.generalise --set dev --objects 1 --models dr" in capsys.readouterr().err
