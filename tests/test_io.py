"""dpc_jax._io: installing a finished folder over an older one."""

from pathlib import Path

from dpc_jax._io import install_folder


def _folder(path: Path, name: str) -> Path:
    path.mkdir()
    (path / name).write_text(name)
    return path


def test_install_folder_replaces_the_older_one_and_leaves_nothing_behind(tmp_path: Path) -> None:
    target = tmp_path / "seq"
    install_folder(_folder(tmp_path / ".seq.tmp-1", "first"), target)
    assert [p.name for p in target.iterdir()] == ["first"]
    install_folder(_folder(tmp_path / ".seq.tmp-2", "second"), target)
    assert [p.name for p in target.iterdir()] == ["second"]
    assert [p.name for p in tmp_path.iterdir()] == ["seq"]
