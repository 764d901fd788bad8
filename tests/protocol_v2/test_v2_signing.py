"""Signed images (PROTOCOL.md § 14.6) on the host and the virtual board: the pure verifier
against RFC 8032 and the cryptography package, the image trailer, key files, keygen and pack,
and the virtual board refusing every forged, tampered, unsigned or downgraded image, also
across a power cut during the security counter's update."""

from __future__ import annotations

import contextlib
import os
import stat

import pytest

from spiel_edge.cli import main
from spiel_edge.device.firmware import update_firmware
from spiel_edge.errors import DeviceError
from spiel_edge.protocol.image import (
    ImageError,
    ImageRefused,
    pack_image,
    parse_image,
    verify_image,
)
from spiel_edge.protocol.signing import (
    DEV_PUBLIC_KEY,
    ed25519_verify,
    key_id,
    parse_public_key_text,
    public_key_text,
)
from spiel_edge.sim.firmware_slots import FACTORY_VERSION, factory_image
from spiel_edge.sim.protocol_sim import device_for_url
from tests.fwsign import DEV_KEY, DEV_PUB, dev_signer, signed_image
from tests.protocol_v2.signing_cases import forged_images, other_signer, raw_upload
from tests.protocol_v2.test_v2_firmware_sim import hello_version

# RFC 8032 § 7.1, tests 1-3: (secret seed, public key, message, signature)
RFC8032 = [
    (
        "9d61b19deffd5a60ba844af492ec2cc44449c5697b326919703bac031cae7f60",
        "d75a980182b10ab7d54bfed3c964073a0ee172f3daa62325af021a68f707511a",
        "",
        "e5564300c360ac729086e2cc806e828a84877f1eb8e5d974d873e06522490155"
        "5fb8821590a33bacc61e39701cf9b46bd25bf5f0595bbe24655141438e7a100b",
    ),
    (
        "4ccd089b28ff96da9db6c346ec114e0f5b8a319f35aba624da8cf6ed4fb8a6fb",
        "3d4017c3e843895a92b70aa74d1b7ebc9c982ccf2ec4968cc0cd55f12af4660c",
        "72",
        "92a009a9f0d4cab8720e820b5f642540a2b27b5416503f8fb3762223ebdb69da"
        "085ac1e43e15996e458f3613d0f11d8c387b2eaeb4302aeeb00d291612bb0c00",
    ),
    (
        "c5aa8df43f9f837bedb7442f31dcb7b166d38535076f094b85ce3a2e0b4458f7",
        "fc51cd8e6218a1a38da47ed00230f0580816ed13ba3303ac5deb911548908025",
        "af82",
        "6291d657deec24024827e69c3abe01a30ce548a284743a445e3680d7db5ac3ac"
        "18ff9b538d16f290ae67f760984dc6594a7c15e9716ed28dc027beceea1ec40a",
    ),
]
BODY = b"SIM:OK " + bytes(range(256)) * 4


def flips(data: bytes, every: int = 1):
    for i in range(0, len(data), every):
        yield data[:i] + bytes([data[i] ^ (1 << (i % 8))]) + data[i + 1 :]


@pytest.mark.parametrize("seed, pk, msg, sig", RFC8032)
def test_the_pure_verifier_takes_rfc8032_and_refuses_each_bit_flip(seed, pk, msg, sig) -> None:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    pk, msg, sig = bytes.fromhex(pk), bytes.fromhex(msg), bytes.fromhex(sig)
    assert Ed25519PrivateKey.from_private_bytes(bytes.fromhex(seed)).sign(msg) == sig
    assert ed25519_verify(pk, msg, sig)
    assert not any(ed25519_verify(pk, msg, s) for s in flips(sig, 7))
    assert not any(ed25519_verify(k, msg, sig) for k in flips(pk, 5))
    assert not ed25519_verify(pk, msg + b"\0", sig)
    assert not ed25519_verify(pk, msg, sig[:63]) and not ed25519_verify(pk[:31], msg, sig)


def test_the_pure_verifier_agrees_with_cryptography() -> None:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
    from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

    for n in range(12):
        key = Ed25519PrivateKey.generate()
        pk = key.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)
        msg = os.urandom(n * 17)
        assert ed25519_verify(pk, msg, key.sign(msg))
    # S >= L (a malleable signature): refused, as Monocypher and OpenSSL refuse it
    sig = bytearray(key.sign(b"x"))
    s = int.from_bytes(sig[32:], "little") + 2**252 + 27742317777372353535851937790883648493
    assert not ed25519_verify(pk, b"x", bytes(sig[:32]) + s.to_bytes(32, "little"))


def test_public_key_file_round_trip_and_the_development_key() -> None:
    assert parse_public_key_text(DEV_PUB.read_text()) == DEV_PUBLIC_KEY
    assert "DEVELOPMENT KEY" in DEV_PUB.read_text() and "DEVELOPMENT KEY" in DEV_KEY.read_text()
    assert dev_signer().public_key == DEV_PUBLIC_KEY
    text = public_key_text(bytes(range(32)), comment="a\nb")
    assert (
        parse_public_key_text(text) == bytes(range(32)) and key_id(bytes(range(32))).hex() in text
    )
    for bad in ("", "0x01,", text.replace("0x1f,", ""), text + "0x00,", text + "junk"):
        with pytest.raises(ValueError):
            parse_public_key_text(bad)


def test_signed_image_layout_and_verify_order(tmp_path) -> None:
    image = signed_image(BODY, version="1.0", target="sim", security_counter=7)
    header = parse_image(image)
    assert (
        header.signed and header.security_counter == 7 and header.key_id == key_id(DEV_PUBLIC_KEY)
    )
    assert len(image) == 96 + len(BODY) + 80 == header.image_size
    assert verify_image(image, DEV_PUBLIC_KEY, 7).version == "1.0"
    for name, (bad, code) in forged_images(image, other_signer(tmp_path)).items():
        with pytest.raises(ImageError) as err:
            verify_image(bad, DEV_PUBLIC_KEY)
        assert isinstance(err.value, ImageRefused) and err.value.code.name == code, name
    with pytest.raises(ImageRefused, match="below the board's 8") as err:
        verify_image(image, DEV_PUBLIC_KEY, 8)
    assert err.value.code.name == "FW_ROLLBACK"
    with pytest.raises(ImageError, match="after its declared end"):
        parse_image(image + b"\0")


def test_the_virtual_boards_factory_image_is_the_development_keys() -> None:
    """Its stored signatures are what keys/dev.key gives (Ed25519 is deterministic)."""
    from spiel_edge.sim.firmware_slots import FACTORY_BODY, TARGET

    for top in (1, 2):
        again = pack_image(
            FACTORY_BODY,
            version=FACTORY_VERSION,
            target=TARGET,
            max_protocol=top,
            signer=dev_signer(),
        )
        assert factory_image(top) == again
        verify_image(again, DEV_PUBLIC_KEY)


def test_keygen_writes_a_private_key_only_its_owner_reads(tmp_path, capsys) -> None:
    name = str(tmp_path / "fleet")
    assert main(["firmware", "keygen", name]) == 0
    mode = stat.S_IMODE(os.stat(name + ".key").st_mode)
    assert mode == 0o600, oct(mode)
    public = parse_public_key_text((tmp_path / "fleet.pub").read_text())
    assert key_id(public).hex() in capsys.readouterr().err
    assert main(["firmware", "keygen", name]) == 2  # never overwritten without --force
    assert "exists" in capsys.readouterr().err
    body = tmp_path / "body.bin"
    body.write_bytes(BODY)
    out = tmp_path / "fw.img"
    pack = ["firmware", "pack", str(body), "--version", "2.0", "--target", "sim", "-o", str(out)]
    assert main([*pack, "--key", name + ".key", "--security-counter", "4", "--release"]) == 0
    assert verify_image(out.read_bytes(), public, 4).security_counter == 4
    assert main([*pack, "--key", str(DEV_KEY), "--release", "--force"]) == 2
    assert "development key" in capsys.readouterr().err
    assert main([*pack, "--key", str(body), "--force"]) == 2
    assert "not an unencrypted Ed25519 private key" in capsys.readouterr().err
    assert main([*pack, "--force"]) == 0  # unsigned: allowed, and said
    assert "UNSIGNED" in capsys.readouterr().err


def test_the_extra_is_named_when_cryptography_is_missing(monkeypatch, tmp_path) -> None:
    import builtins

    real = builtins.__import__

    def no_crypto(name, *args, **kwargs):
        if name.startswith("cryptography"):
            raise ImportError(name)
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_crypto)
    from spiel_edge.device.fwkeys import load_private_key
    from spiel_edge.errors import InputError

    with pytest.raises(InputError, match=r"'sign' extra: pip install 'spiel-edge\[sign\]'"):
        load_private_key(DEV_KEY)


def test_the_virtual_board_refuses_forged_images(sim_url, tmp_path) -> None:
    url = sim_url()
    good = signed_image(BODY, version="sim-0.2.0", target="sim", security_counter=3)
    for name, (bad, code) in forged_images(good, other_signer(tmp_path)).items():
        assert raw_upload(url, bad) == code, name
    assert raw_upload(url, good) is None


def test_the_host_says_in_one_line_why_the_board_refused(sim_url, tmp_path) -> None:
    url = sim_url()
    good = signed_image(BODY, version="sim-0.2.0", target="sim")
    wrong, _ = forged_images(good, other_signer(tmp_path))["wrong key"]
    with pytest.raises(DeviceError) as err:
        update_firmware(url, wrong, boot_wait_s=5)
    line = str(err.value)
    assert "\n" not in line and "FW_WRONG_KEY" in line and "keeps firmware sim-0.1.0" in line
    unsigned = pack_image(BODY, version="sim-0.2.0", target="sim")
    ops = device_for_url(url).board.fw.ops
    with pytest.raises(DeviceError, match="not signed"):  # refused before a byte is sent
        update_firmware(url, unsigned, boot_wait_s=5)
    assert device_for_url(url).board.fw.ops == ops


def test_a_downgrade_is_refused_once_a_higher_counter_is_confirmed(sim_url) -> None:
    url = sim_url()
    v5 = signed_image(BODY, version="sim-0.5.0", target="sim", security_counter=5)
    v3 = signed_image(BODY + b"!", version="sim-0.3.0", target="sim", security_counter=3)
    assert update_firmware(url, v3, boot_wait_s=10).confirmed  # 0 -> 3: an upgrade
    assert update_firmware(url, v5, boot_wait_s=10).confirmed
    assert device_for_url(url).board.fw.record().security_counter == 5
    with pytest.raises(DeviceError, match="FW_ROLLBACK") as err:
        update_firmware(url, v3, boot_wait_s=10)
    assert "security counter 3 is below the board's 5" in str(err.value)
    # the old image still in the other slot is never booted again either
    fw = device_for_url(url).board.fw
    assert fw.header(1 - fw.running).security_counter == 3
    assert fw.bootable(1 - fw.running, 5) is None
    same = signed_image(BODY + b"!!", version="sim-0.5.1", target="sim", security_counter=5)
    assert update_firmware(url, same, boot_wait_s=10).confirmed  # equal: allowed


def test_a_power_cut_during_the_counters_update_keeps_old_or_new(sim_url) -> None:
    """The counter rises in FW_CONFIRM's record write (one operation on the virtual board's
    flash): cut there, the board comes back with the old image and the old counter (a v3
    image still accepted), past it with the new image and counter (v3 refused), never the new
    image with the old counter."""
    v5 = signed_image(BODY, version="sim-0.5.0", target="sim", security_counter=5)
    v3 = signed_image(BODY + b"!", version="sim-0.3.0", target="sim", security_counter=3)
    count = sim_url()
    assert update_firmware(count, v5, boot_wait_s=10).confirmed
    ops = device_for_url(count).board.fw.ops  # the confirm record is the last operation
    seen = set()
    for cut in (ops - 1, None):  # cut in the confirm's record write, or no cut
        url = sim_url(f"fw_power_cut={cut}" if cut is not None else "")
        with contextlib.suppress(DeviceError):  # cut mid-request: the board vanishes
            update_firmware(url, v5, boot_wait_s=6)
        version = hello_version(url)
        fw = device_for_url(url).board.fw
        seen.add(version)
        refused = raw_upload(url, v3)
        if version == "sim-0.5.0":
            assert fw.record().security_counter == 5 and refused == "FW_ROLLBACK", cut
        else:
            assert version == FACTORY_VERSION and fw.record().security_counter == 0, cut
            assert refused is None, cut
    assert seen == {FACTORY_VERSION, "sim-0.5.0"}


def test_check_says_whether_a_board_would_accept_an_image(tmp_path, capsys) -> None:
    image = tmp_path / "fw.img"
    image.write_bytes(signed_image(BODY, version="1.0", target="sim", security_counter=4))
    check = ["firmware", "check", str(image), "--pub", str(DEV_PUB)]
    assert main(check) == 0
    assert "a board with this key accepts it" in capsys.readouterr().err
    assert main([*check, "--min-counter", "5"]) == 2
    assert "FW_ROLLBACK" in capsys.readouterr().err
    other_signer(tmp_path)
    assert main([*check[:3], "--pub", str(tmp_path / "other.pub")]) == 2
    assert "FW_WRONG_KEY" in capsys.readouterr().err
    assert main([*check[:3], "--pub", str(image)]) == 2  # not a key file
    assert "not a public key file" in capsys.readouterr().err
