"""Damaged images reach `prepare` as one-line errors naming the file, never as silently
different features."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from uevavd.perception.images import ImageReadError, read_rgb


def test_a_truncated_jpeg_is_refused_not_filled_with_gray(tmp_path):
    img = (np.random.default_rng(0).random((64, 64, 3)) * 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", img)
    good = tmp_path / "good.jpg"
    good.write_bytes(buf.tobytes())
    assert read_rgb(good).shape == (64, 64, 3)
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(buf.tobytes()[: len(buf) // 2])
    assert cv2.imread(str(cut)) is not None  # what OpenCV alone does: decodes it, gray-filled
    with pytest.raises(ImageReadError, match=r"cut.jpg: truncated JPEG"):
        read_rgb(cut)


def test_an_absurd_png_header_is_a_read_error_not_a_cv2_error(tmp_path):
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    huge = tmp_path / "huge.png"
    huge.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 60000, 60000, 8, 2, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(b"\x00" * 10)) + chunk(b"IEND", b""))
    with pytest.raises(ImageReadError, match="huge.png: cannot be decoded"):
        read_rgb(huge)
    from uevavd.data.validate import check_image_bytes

    size, err = check_image_bytes(huge.read_bytes(), huge)
    assert size is None and "cannot be decoded" in err


def test_prepare_reports_a_truncated_view_in_one_line(tiny_world, tiny_classifier, method_toml, tmp_path, capsys,
                                                      monkeypatch):
    import shutil

    from uevavd.cli import main

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    world = tmp_path / "world"
    shutil.copytree(tiny_world, world)
    victim = sorted((world / "031").glob("*.png"))[7]
    victim.write_bytes(victim.read_bytes()[:-40])
    method = tmp_path / "m.toml"
    method.write_text(method_toml.format(decompose="false"))
    rc = main(["prepare", str(world), "--method", str(method), "--classifier", str(tiny_classifier),
               "--out", str(tmp_path / "tables"), "--workers", "1"])
    err = capsys.readouterr().err.strip()
    last = err.splitlines()[-1]  # after the progress bar's own line, which it ends
    assert rc == 2 and "Traceback" not in err and last.startswith("uevavd prepare: error: "), err
    assert victim.name in last and "truncated PNG" in last, err


def test_a_recognizer_of_another_crop_size_is_refused(tiny_world, tiny_classifier, method_toml, tmp_path):
    """A 16 px recognizer on a 24 px world used to build a table without a word."""
    import json

    from uevavd.perception.classifier import read_classifier_file, write_classifier_file
    from uevavd.perception.prepare import prepare_table

    sd, meta = read_classifier_file(tiny_classifier)
    other = write_classifier_file(tmp_path / "c24.safetensors", sd, {**meta, "input_size": [24, 24]})
    method = tmp_path / "m.toml"
    method.write_text(method_toml.format(decompose="false"))
    with pytest.raises(ValueError, match=r"trained on 24 x 24 px crops, but .* holds 16 x 16 px views"):
        prepare_table(tiny_world, method, classifier_path=other, out_dir=tmp_path / "t", progress=False)
    assert json.dumps(meta["input_size"]) == "[16, 16]"


@pytest.mark.parametrize("option, value", [("--threads", "-2"), ("--workers", "0"), ("--shards", "0")])
def test_prepare_refuses_a_count_below_one_in_one_line(tiny_world, method_toml, tmp_path, capsys, monkeypatch,
                                                      option, value):
    """``prepare --threads -2`` was torch's traceback; every count is refused before any work."""
    from uevavd.cli import main

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    method = tmp_path / "m.toml"
    method.write_text(method_toml.format(decompose="false"))
    rc = main(["prepare", str(tiny_world), "--method", str(method), "--out", str(tmp_path / "tables"), option, value])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.count("\n") == 0 and f"{option} {value}: expected at least 1" in err, err
    assert not (tmp_path / "tables").exists()


def test_a_file_size_limit_during_prepare_is_one_line(tiny_world, tiny_classifier, method_toml, tmp_path, capsys,
                                                     monkeypatch):
    """`ulimit -f` below a cache's or the table's size: numpy's short write ("N requested and M
    written", no errno) was a traceback. The limit is this process's own for the command (Python
    ignores SIGXFSZ, so a write past it fails with EFBIG, as in a shell under `ulimit -f`)."""
    import resource

    from uevavd.cli import main

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    method = tmp_path / "m.toml"
    method.write_text(method_toml.format(decompose="false"))
    out = tmp_path / "tables"
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, hard))
    try:
        rc = main(["prepare", str(tiny_world), "--method", str(method), "--classifier", str(tiny_classifier),
                   "--out", str(out), "--workers", "1"])
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    stderr = capsys.readouterr().err
    err = [line for line in stderr.splitlines() if "uevavd prepare: error" in line]
    assert rc == 2 and "Traceback" not in stderr and len(err) == 1, stderr
    assert "File too large" in err[0] or "file-size limit of 200,000 bytes" in err[0], err
    assert str(out) in err[0] and "raise it, or write elsewhere" in err[0], err
    assert not [f for f in out.rglob("*") if f.name.startswith(".") and ".tmp" in f.name]


def test_a_full_disk_in_the_tables_final_save_is_enospc(tmp_path, monkeypatch):
    import errno
    import shutil
    from collections import namedtuple

    from uevavd.testing.policy import toy_table

    table = toy_table(n_train=2, n_hard=1, feature_dim=8)
    real = np.save

    def short(fh, arr, *a, **k):
        if arr.ndim == 3:  # the features
            raise OSError("1048576 requested and 4096 written")
        return real(fh, arr, *a, **k)

    monkeypatch.setattr(np, "save", short)
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10**9, 10**9 - 4096, 4096))
    with pytest.raises(OSError) as err:
        table.save(tmp_path / "t")
    assert err.value.errno == errno.ENOSPC and str(tmp_path) in str(err.value)
    assert list(tmp_path.iterdir()) == []  # neither the table nor its temporary folder
