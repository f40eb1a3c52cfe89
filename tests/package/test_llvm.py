"""libLLVM discovery, on fake directory trees."""
import pytest

from mitsuba_plugins import _llvm


def touch(path):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"")
    return path


def test_parses_debian_and_versioned_names():
    f = _llvm.llvm_major_from_path
    assert f("/usr/lib/x86_64-linux-gnu/libLLVM-19.so") == 19
    assert f("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1") == 19
    assert f("/usr/lib/x86_64-linux-gnu/libLLVM-14.0.6.so.1") == 14
    assert f("/usr/lib/llvm-17/lib/libLLVM.so") == 17
    assert f("/opt/homebrew/opt/llvm/lib/libLLVM.18.dylib") == 18
    assert f("/usr/lib/libLLVMSupport.a") is None
    assert f("/usr/lib/libLLVM.so") is None


def test_newest_suitable_wins(tmp_path):
    touch(tmp_path / "a" / "libLLVM-15.so")
    touch(tmp_path / "a" / "libLLVM.so.19.1")
    touch(tmp_path / "llvm-17" / "lib" / "libLLVM.so")
    chosen = _llvm.choose_llvm([str(tmp_path / "a"), str(tmp_path / "llvm-*" / "lib")])
    assert chosen.major == 19 and chosen.path.endswith("libLLVM.so.19.1")


def test_symlinks_to_one_file_count_once(tmp_path):
    real = touch(tmp_path / "libLLVM.so.19.1")
    (tmp_path / "libLLVM-19.so").symlink_to(real)
    assert len(_llvm.find_candidates([str(tmp_path)])) == 1


def test_only_broken_versions_names_the_fix(tmp_path):
    touch(tmp_path / "libLLVM-15.so")
    touch(tmp_path / "libLLVM-14.so.1")
    with pytest.raises(_llvm.LLVMNotFoundError) as err:
        _llvm.choose_llvm([str(tmp_path)])
    msg = str(err.value)
    assert "apt-get install -y libllvm19" in msg and "DRJIT_LIBLLVM_PATH" in msg
    assert "LLVM 15" in msg  # says what it found and rejected


def test_nothing_found(tmp_path):
    with pytest.raises(_llvm.LLVMNotFoundError, match="libllvm19"):
        _llvm.choose_llvm([str(tmp_path / "missing")])


def test_environment_set_only_when_unset(tmp_path):
    touch(tmp_path / "libLLVM-19.so")
    env = {}
    assert _llvm.configure_environment(env, [str(tmp_path)]) == str(tmp_path / "libLLVM-19.so")
    assert env[_llvm.ENV_VAR] == str(tmp_path / "libLLVM-19.so")
    env = {_llvm.ENV_VAR: "/mine/libLLVM.so"}
    assert _llvm.configure_environment(env, [str(tmp_path)]) == "/mine/libLLVM.so"
    env = {}
    assert _llvm.configure_environment(env, [str(tmp_path / "missing")]) is None
    assert _llvm.ENV_VAR not in env


def test_already_loaded_llvm15_is_refused():
    with pytest.raises(_llvm.LLVMNotFoundError, match="Dr.Jit loaded LLVM 15.0.7"):
        _llvm.check_loaded_llvm((15, 0, 7))
    _llvm.check_loaded_llvm((19, 1, 7))


@pytest.mark.llvm_only
def test_this_process_uses_a_working_llvm():
    import drjit as dr
    assert dr.detail.llvm_version()[0] >= _llvm.MIN_LLVM_MAJOR
