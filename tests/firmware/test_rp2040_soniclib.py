"""The RP2040 target's CH101 sensor layer over TDK SonicLib (targets/rp2040/sensor/).

What runs without hardware:
- the pure logic (iq_plan.c, built on the host): I/Q to envelope samples (round(sqrt(q^2+i^2)),
  checked against numpy), I/Q to the protocol's I16_IQ words, and the I2C time budget showing
  4 x 64 I/Q at >= 50 acquisitions/s on two 400 kHz buses (and not on one);
- the acquisition flow of sensor_soniclib.c through SonicLib's own non-blocking queue, on the
  host with a fake two-bus board (soniclib_host/harness.c; needs SPIEL_SONICLIB_DIR);
- the build: ``make TARGET=rp2040 SONICLIB_DIR=...`` against a SonicLib checkout given by
  SPIEL_SONICLIB_DIR (skipped without it or without arm-none-eabi-gcc; SonicLib is never
  vendored: its licence restricts it to TDK sensors), our files with every warning an error,
  the sensor's interrupts in the vector table, the non-blocking read ours (not SonicLib's
  weak stub); and without SONICLIB_DIR the one-line notice.
What needs a board (four CH101 wired as docs/build-a-board.md says) is listed in
docs/firmware.md ("The SonicLib sensor layer on the Pico")."""

from __future__ import annotations

import ctypes
import os
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
FIRMWARE = ROOT / "firmware_protocol" / "firmware"
SENSOR = FIRMWARE / "targets" / "rp2040" / "sensor"
BUS_OF_PICO = (0, 0, 1, 1)  # chbsp_rp2040.h: sensors 0, 1 on I2C0; 2, 3 on I2C1
I2C_HZ = 400_000


class IqPair(ctypes.Structure):
    _fields_ = [("q", ctypes.c_int16), ("i", ctypes.c_int16)]


@pytest.fixture(scope="module")
def plan(tmp_path_factory):
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler (cc)")
    so = tmp_path_factory.mktemp("iq_plan") / "iq_plan.so"
    warn = "-std=c99 -Wall -Wextra -Werror -pedantic -Wconversion -Wsign-conversion -Wshadow"
    subprocess.run(
        [cc, *warn.split(), "-O2", "-shared", "-fPIC", str(SENSOR / "iq_plan.c"), "-o", str(so)],
        check=True,
        capture_output=True,
    )
    lib = ctypes.CDLL(str(so))
    lib.iq_magnitude.restype = ctypes.c_uint16
    lib.iq_magnitude.argtypes = [ctypes.c_int16, ctypes.c_int16]
    lib.iq_i2c_read_ns.restype = ctypes.c_uint32
    lib.iq_i2c_read_ns.argtypes = [ctypes.c_uint32, ctypes.c_uint32]
    args = [ctypes.c_uint32, ctypes.c_uint16]
    bus = [ctypes.POINTER(ctypes.c_uint8), ctypes.c_uint8, ctypes.c_uint8, ctypes.c_uint32]
    lib.iq_acq_read_us.restype = ctypes.c_uint32
    lib.iq_acq_read_us.argtypes = args + bus
    lib.iq_acq_rate_centi.restype = ctypes.c_uint32
    lib.iq_acq_rate_centi.argtypes = args + [ctypes.c_uint32] + bus + [ctypes.c_uint32]
    return lib


def _pairs(q: np.ndarray, i: np.ndarray):
    arr = (IqPair * len(q))()
    for k, (a, b) in enumerate(zip(q.tolist(), i.tolist(), strict=True)):
        arr[k].q, arr[k].i = a, b
    return arr


def test_magnitude_is_the_rounded_envelope(plan):
    rng = np.random.default_rng(7)
    q = np.concatenate([[0, -32768, 32767, -32768, 3, 1, -1], rng.integers(-32768, 32768, 4000)])
    i = np.concatenate([[0, -32768, 32767, 0, 4, 1, 0], rng.integers(-32768, 32768, 4000)])
    q, i = q.astype(np.int16), i.astype(np.int16)
    want = np.floor(np.hypot(q.astype(np.float64), i.astype(np.float64)) + 0.5)
    n = len(q)
    out = (ctypes.c_uint16 * n)()
    plan.iq_magnitudes(_pairs(q, i), out, ctypes.c_uint16(n))
    got = np.frombuffer(out, dtype=np.uint16)
    np.testing.assert_array_equal(got, want.astype(np.uint16))
    assert got.max() == 46341  # (-32768, -32768): fits 16 bits, no wrap
    assert plan.iq_magnitude(3, 4) == 5


def test_iq_words_are_q_then_i_twos_complement(plan):
    q = np.array([1, -2, 32767, -32768], dtype=np.int16)
    i = np.array([-1, 300, 0, 5], dtype=np.int16)
    out = (ctypes.c_uint16 * 8)()
    plan.iq_words(_pairs(q, i), out, ctypes.c_uint16(4))
    words = bytes(out)
    # what a STREAM_DATA I16_IQ payload carries (little-endian int16 q0 i0 q1 i1 ...)
    assert struct.unpack("<8h", words) == (1, -1, -2, 300, 32767, 0, -32768, 5)


def _bus(buses):
    return (ctypes.c_uint8 * len(buses))(*buses)


def test_i2c_read_time_of_one_sensor(plan):
    # 64 I/Q samples = 256 bytes, plus address+W, register, address+R: 259 bytes of 9 clocks,
    # and START, repeated START, STOP: 2,334 clocks at 400 kHz = 5,835 us
    assert plan.iq_i2c_read_ns(256, I2C_HZ) == 5_835_000
    assert plan.iq_i2c_read_ns(0, I2C_HZ) == (3 * 9 + 3) * 2500


def test_two_buses_carry_50_acquisitions_per_second_one_does_not(plan):
    mask, n, fs = 0xF, 64, 21_997  # CH101: 175.98 kHz / 8
    two = plan.iq_acq_read_us(mask, n, _bus(BUS_OF_PICO), 4, 2, I2C_HZ)
    one = plan.iq_acq_read_us(mask, n, _bus((0, 0, 0, 0)), 4, 1, I2C_HZ)
    assert two == 2 * 5835 and one == 4 * 5835
    # a trigger, the INT edges, the reads' start and the interrupts: 1 ms allowed per acquisition
    rate_two = plan.iq_acq_rate_centi(mask, n, fs, _bus(BUS_OF_PICO), 4, 2, I2C_HZ, 1000) / 100
    rate_one = plan.iq_acq_rate_centi(mask, n, fs, _bus((0, 0, 0, 0)), 4, 1, I2C_HZ, 1000) / 100
    assert rate_two >= 50 > rate_one
    assert 64 < rate_two < 66 and 36 < rate_one < 38
    # a subset reads only its sensors: channels 0 and 2 are one read on each bus
    assert plan.iq_acq_read_us(0b0101, n, _bus(BUS_OF_PICO), 4, 2, I2C_HZ) == 5835


def _make(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(
        ["make", *args], cwd=FIRMWARE, capture_output=True, text=True, timeout=timeout
    )


def test_without_soniclib_the_build_says_so_in_one_line():
    if shutil.which("make") is None:
        pytest.skip("make not found")
    done = _make("-n", "TARGET=rp2040", "BUILD=/nonexistent-build")
    notes = [ln for ln in done.stdout.splitlines() if ln.startswith("rp2040:")]
    assert notes == [
        "rp2040: no SONICLIB_DIR: no sensor layer, the firmware streams its embedded recordings"
    ]
    bad = _make("-n", "TARGET=rp2040", "SONICLIB_DIR=/nonexistent-soniclib")
    assert bad.returncode != 0
    assert "holds no invn/soniclib/soniclib.h" in bad.stderr


def _symbols(elf: Path) -> dict[str, tuple[int, str]]:
    out = subprocess.run(
        ["arm-none-eabi-nm", str(elf)], capture_output=True, text=True, check=True
    ).stdout
    syms = {}
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 3:
            syms[parts[2]] = (int(parts[0], 16), parts[1])
    return syms


def test_builds_against_a_soniclib_checkout(tmp_path):
    sl = os.environ.get("SPIEL_SONICLIB_DIR")
    if not sl:
        pytest.skip("SPIEL_SONICLIB_DIR not set (a checkout of tdk-invn-oss/ultrasonic.soniclib)")
    for tool in ("make", "arm-none-eabi-gcc", "arm-none-eabi-nm"):
        if shutil.which(tool) is None:
            pytest.skip(f"{tool} not found (gcc-arm-none-eabi, libnewlib-arm-none-eabi)")
    build = tmp_path / "rp2040-soniclib"
    done = _make("TARGET=rp2040", f"SONICLIB_DIR={sl}", f"BUILD={build}")
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert f"rp2040: the CH101 sensor layer over SonicLib in {sl}" in done.stdout
    assert (build / "firmware.uf2").stat().st_size > 0
    assert not (build / "firmware-emu.uf2").exists()  # no emulator image: no sensor there
    # our sensor files with every warning an error, SonicLib's with its own flags
    ours = [ln for ln in done.stdout.splitlines() if "sensor_soniclib.c" in ln and " -c " in ln]
    assert ours and "-Werror" in ours[0] and "-Wconversion" in ours[0]
    theirs = [ln for ln in done.stdout.splitlines() if "ch_driver.c" in ln and " -c " in ln]
    assert theirs and "-Werror" not in theirs[0]
    syms = _symbols(build / "app.elf")
    for name in ("ch_group_trigger", "ch_get_iq_data", "ch_io_start_nb", "hal_acq_read_iq"):
        assert name in syms, name
    assert syms["chbsp_i2c_mem_read_nb"][1] == "T"  # ours, not chbsp_dummy.c's weak one
    # the vector table (at the application's start) sends the sensor's interrupts to us:
    # IO_IRQ_BANK0 (13), I2C0_IRQ (23), I2C1_IRQ (24), entries 16 + n, Thumb bit set (the
    # SDK's intctrl.h names isr_io_bank0, isr_i2c0, isr_i2c1 isr_irq13, isr_irq23, isr_irq24)
    image = (build / "app.bin").read_bytes()
    vectors = struct.unpack_from("<48I", image, 0)
    for irq in (13, 23, 24):
        isr = f"isr_irq{irq}"
        assert syms[isr][1] == "T", isr  # defined by chbsp_rp2040.c, not the weak default
        assert vectors[16 + irq] == syms[isr][0] | 1, isr
        assert vectors[16 + irq] != vectors[16 + 1]  # not the unused-interrupt trap


SONICLIB_SOURCES = (
    "ch_api",
    "ch_common",
    "ch_driver",
    "ch_math_utils",
    "ch_rangefinder",
    "chbsp_dummy",
    "sensor_fw/ch101/ch101_gpr",
    "sensor_fw/ch101/ch101_gpr_fw",
)


def test_acquisition_flow_through_soniclib_on_two_buses(tmp_path):
    """sensor_soniclib.c and SonicLib's own non-blocking queue on the host, a fake board in
    place of chbsp_rp2040.c (tests/firmware/soniclib_host/harness.c): the reads wait for the
    mask's last interrupt, both buses start at once, each bus reads its two sensors one after
    the other, ready only after the last; triggers are refused meanwhile; I/Q and envelopes
    come out of the sensors' data; a hung bus fails the acquisition at its deadline and the
    next one works (SonicLib's queue reset)."""
    sl = os.environ.get("SPIEL_SONICLIB_DIR")
    if not sl:
        pytest.skip("SPIEL_SONICLIB_DIR not set (a checkout of tdk-invn-oss/ultrasonic.soniclib)")
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler (cc)")
    host = ROOT / "tests" / "firmware" / "soniclib_host"
    defs = ["-DINCLUDE_WHITNEY_SUPPORT", "-DCH_LOG_MODULE_LEVEL=6"]
    objs = []
    for src in SONICLIB_SOURCES:
        obj = tmp_path / (Path(src).name + ".o")
        # SonicLib with its own (relaxed) warnings; ch_group_start is the harness's
        rename = ["-Dch_group_start=soniclib_ch_group_start"] if src == "ch_api" else []
        subprocess.run(
            [cc, "-std=gnu99", "-O1", "-ffunction-sections", *defs, *rename, f"-I{SENSOR}",
             f"-I{sl}", "-c", f"{sl}/invn/soniclib/{src}.c", "-o", str(obj)],
            check=True, capture_output=True,
        )  # fmt: skip
        objs.append(str(obj))
    exe = tmp_path / "harness"
    warn = [
        "-std=gnu11",
        "-Wall",
        "-Wextra",
        "-Werror",
        "-Wconversion",
        "-Wsign-conversion",
        "-Wshadow",
    ]
    built = subprocess.run(
        [cc, *warn, "-O1", "-ffunction-sections", "-Wl,--gc-sections", *defs,
         "-DSPIEL_IQ_SAMPLES=1", f"-I{host}", f"-I{SENSOR}", f"-I{FIRMWARE / 'include'}",
         "-isystem", sl, str(host / "harness.c"), str(SENSOR / "sensor_soniclib.c"),
         str(SENSOR / "iq_plan.c"), *objs, "-o", str(exe)],
        capture_output=True, text=True,
    )  # fmt: skip
    assert built.returncode == 0, built.stderr[-3000:]
    done = subprocess.run([str(exe)], capture_output=True, text=True, timeout=60)
    lines = done.stdout.splitlines()
    assert done.returncode == 0, done.stdout[-3000:]
    assert not [ln for ln in lines if not ln.startswith("ok ")]
    assert len(lines) == 29  # every check of harness.c ran
    assert "ok both buses start reading at once" in lines
    assert "ok SonicLib's queue was emptied: both buses start afresh" in lines
