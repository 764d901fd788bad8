import json

from spiel_edge.cli import main


def test_bench_json_is_the_last_line_with_stage_timings(capsys):
    assert (
        main(
            [
                "bench",
                "--json",
                "--repeat",
                "1",
                "--no-startup",
                "--association",
                "geometric",
                "--reference",
                "1",
            ]
        )
        == 0
    )
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    stages = ("preprocess", "detect", "memg", "features", "associate", "echo_timing", "locate")
    for key in ("real_4x64", "synthetic_8x256", "synthetic_16x1024"):
        block = result[key]
        assert block["acquisitions"] > 0
        for stage in (*stages, "end_to_end"):
            assert 0 < block[stage]["median_us"] <= block[stage]["p95_us"]
        assert block["end_to_end"]["median_us"] >= block["memg"]["median_us"]
    assert result["end_to_end"] == result["real_4x64"]["end_to_end"]
    assert result["association"] == "geometric"
    for key in ("paths_4x64", "paths_8x256", "paths_16x1024"):
        block = result[key]
        assert 0 < block["fused"]["median_us"] <= block["fused"]["p95_us"]
        assert block["staged_over_fused"] > 0
    ref = result["reference_4x64"]
    assert ref["available"] and ref["acquisitions"] == 1 and ref["reference_over_fused"] > 1
    scene = result["scene_4_tracked"]
    assert scene["k"] == 4 and scene["acquisitions"] > 0
    assert 0 < scene["median_us"] <= scene["p95_us"]


def test_peak_memory_of_a_fresh_run_and_failures_raise():
    import pytest

    from spiel_edge.measure.bench import peak_rss_mib

    small = peak_rss_mib(("run", "--port", "sim://", "--frames", "2", "--rate", "0", "-o", "-"))
    assert 30 < small < 2000  # an interpreter with numpy and numba, in MiB (not KiB, not bytes)
    with pytest.raises(RuntimeError, match="exited with 2"):
        peak_rss_mib(("run", "--no-such-option"))


def test_a_paced_run_over_a_pty_wakes_about_once_per_acquisition():
    """At the board's 50/s the host waits for each acquisition's bytes in one select: no
    polling with short timeouts (issue 39's suspect for CPU per record at 50/s)."""
    from spiel_edge.measure.bench_run import run_path_cpu

    run = run_path_cpu(100, 50.0)
    assert run["records"] == 100 and run["rate_hz"] == 50.0
    assert run["cpu_us_per_record"] > 0
    # a wait per acquisition (fewer when two arrive together on a loaded machine), plus the
    # link's keeping (TIME_SYNC every 0.1-0.25 s, heartbeats): well under 2 per record
    assert 0 < run["wakeups_per_record"] < 2.0
