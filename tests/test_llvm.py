"""risp_data.llvm: finding a libLLVM that Dr.Jit can drive, and one clear line when there is none."""

from __future__ import annotations

import pytest

from risp_data import llvm
from risp_data.errors import RispError


@pytest.fixture
def no_preset(monkeypatch):
    # setenv first so that monkeypatch records the variable even when it was unset: ensure_llvm() writes it, and
    # without a record the test's bogus path would outlive the test (and break the next Mitsuba start-up)
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "unset-by-test")
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH")


@pytest.mark.parametrize("name, major", [
    ("libLLVM.so.19.1", 19),
    ("libLLVM-19.so", 19),
    ("libLLVM-15.so.1", 15),
    ("libLLVM-14.0.6.so.1", 14),
    ("libLLVM.19.dylib", 19),
    ("/usr/lib/x86_64-linux-gnu/libLLVM-17.so.1", 17),
    ("/usr/lib/llvm-19/lib/libLLVM.so.1", 19),  # the ".1" is an ABI number: the folder names the version
    ("libLLVM.so", None),
    ("libLLVM.so.1", None),
])
def test_major_version_parsing(name, major):
    assert llvm._major(name) == major


def test_no_library_at_all_is_one_clear_line(monkeypatch, no_preset):
    monkeypatch.setattr(llvm, "candidate_libraries", lambda: [])
    with pytest.raises(RispError, match=r"no libLLVM >= 16 found .*found: none.*apt-get install libllvm19") as e:
        llvm.ensure_llvm()
    assert "\n" not in str(e.value)


def test_only_llvm_15_is_refused(monkeypatch, no_preset):
    monkeypatch.setattr(llvm, "candidate_libraries", lambda: ["/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1"])
    with pytest.raises(RispError, match=r"no libLLVM >= 16 found .*found: LLVM 15\)") as e:
        llvm.ensure_llvm()
    assert "\n" not in str(e.value)


def test_newest_candidate_is_chosen(monkeypatch, no_preset):
    cands = ["/x/libLLVM.so.19.1", "/x/libLLVM-17.so", "/x/libLLVM-15.so.1"]
    monkeypatch.setattr(llvm, "candidate_libraries", lambda: cands)
    assert llvm.ensure_llvm() == "/x/libLLVM.so.19.1"
    import os

    assert os.environ["DRJIT_LIBLLVM_PATH"] == "/x/libLLVM.so.19.1"


def test_preset_path_is_checked(monkeypatch, tmp_path):
    old = tmp_path / "libLLVM-15.so.1"
    old.write_bytes(b"")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(old))
    with pytest.raises(RispError, match=r"DRJIT_LIBLLVM_PATH=.*libLLVM-15\.so\.1 is LLVM 15, but Dr\.Jit needs LLVM >= 16") as e:
        llvm.ensure_llvm()
    assert "\n" not in str(e.value)
    good = tmp_path / "libLLVM-19.so"
    good.write_bytes(b"")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(good))
    assert llvm.ensure_llvm() == str(good)
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(tmp_path / "missing.so"))
    with pytest.raises(RispError, match="does not exist"):
        llvm.ensure_llvm()
