import json
import stat

from spiel_edge.cli import main
from spiel_edge.runtime import warmup
from spiel_edge.service import kit


def test_one_kernel_finder_sees_the_fused_and_staged_kernels():
    names = set(warmup.pipeline_kernels())
    kernels = (
        "compiled.front._front_kernel",
        "stages.memg.memg_kernel",
        "stages.split.split_kernel",
    )
    for kernel in (
        *kernels,
        "stages.associate.hypothesis_kernel",
        "compiled.several_targets._scene_acquisition_kernel",
        "learned.mlp.mlp_scores",
    ):
        assert f"spiel_edge.pipeline.{kernel}" in names


def test_warmup_command_reports(monkeypatch, capsys):
    report = {"seconds": 1.5, "kernels": 11, "compiled": ["a"], "cache_hits": [], "cache_dir": "/c"}
    monkeypatch.setattr(warmup, "warmup", lambda **_: report)
    assert main(["warmup"]) == 0
    assert (
        "11 kernels in 1.5 s: 1 compiled, 0 loaded from the cache (/c)" in capsys.readouterr().out
    )
    assert main(["warmup", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == report


def test_service_install_warms_the_units_cache(tmp_path, capsys, monkeypatch):
    from spiel_edge.service import sandbox

    # the fake program lives under /tmp, which the unit's PrivateTmp hides (tests/security
    # checks that refusal); here only the warm-up is under test
    monkeypatch.setattr(sandbox, "TMP_DIRS", ())
    fake = tmp_path / "spiel-edge"
    fake.write_text(
        "#!/bin/sh\n"
        'echo "{\\"kernels\\": 3, \\"seconds\\": 0.5, \\"compiled\\": [], \\"cache\\": \\"$NUMBA_CACHE_DIR\\"}"\n'
    )
    fake.chmod(fake.stat().st_mode | stat.S_IEXEC)
    report = kit.warm_cache(str(fake), tmp_path)
    assert report["cache"] == str(tmp_path / kit.CACHE_PATH)
    root = tmp_path / "root"
    assert main(["service", "install", "--prefix", str(root), "--exec", str(fake), "--warmup"]) == 0
    assert "warmed" in capsys.readouterr().out and (root / kit.CACHE_PATH).is_dir()
    assert main(["service", "install", "--prefix", str(tmp_path / "r2"), "--exec", str(fake)]) == 0
    assert "warmed" not in capsys.readouterr().out  # not / : off unless asked
