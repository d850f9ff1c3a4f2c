"""The package re-exports its public API lazily and every name resolves."""

import subprocess
import sys

import dpc_jax


def test_every_exported_name_resolves() -> None:
    for name in dpc_jax.__all__:
        assert getattr(dpc_jax, name) is not None, name


def test_import_is_light() -> None:
    code = "import sys, dpc_jax; print('jax' in sys.modules, 'flax' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]


def test_no_export_shadows_a_submodule() -> None:
    import pkgutil

    submodules = {m.name for m in pkgutil.iter_modules(dpc_jax.__path__)}
    assert submodules.isdisjoint(dpc_jax.__all__)


def test_data_package_reexports_lazily_and_its_file_readers_are_light() -> None:
    import dpc_jax.data

    for name in dpc_jax.data.__all__:
        assert getattr(dpc_jax.data, name) is not None, name
    # The command line reads trajectories before it imports JAX (and OpenCV is not needed for them).
    code = "import sys, dpc_jax.data.poses_io; print('jax' in sys.modules, 'cv2' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]


def test_training_configs_are_checked_without_jax() -> None:
    # The command line checks a training config before it imports JAX: the checks of the model and
    # loss overrides must not pull in the networks.
    code = (
        "import sys\n"
        "from dpc_jax.config import ConfigError\n"
        "from dpc_jax.training.train_config import TrainConfig\n"
        "for fields in ({'preset': 'tiny'}, {'model': {'encoder_kernels': [2]}}, {'loss': {'beta': 1}}):\n"
        "    try:\n"
        "        TrainConfig(cache_root='c', validation_sequences=('v',), **fields)\n"
        "    except ConfigError as error:\n"
        "        print(str(error).split(':')[0])\n"
        "print([m for m in ('jax', 'flax', 'cv2') if m in sys.modules])\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    preset = "preset must be one of ['reference', 'small'], got 'tiny'"
    assert out.splitlines() == [preset, "model", "loss", "[]"]


def test_the_face_is_the_one_the_architecture_page_names() -> None:
    """Each exported name is listed, in backticks, in docs/architecture.md's "The public face", and that
    section lists no other dpc_jax function or class (a name added or dropped changes both)."""
    import re
    from pathlib import Path

    page = (Path(__file__).resolve().parents[1] / "docs" / "architecture.md").read_text()
    section = page.split("## The public face", 1)[1].split("\n## ", 1)[0]
    listed = set(re.findall(r"\* \*\*[^*]+\*\*: (.*?)(?=\n\* |\n\n)", section, flags=re.S))
    names = {n for text in listed for n in re.findall(r"`([A-Za-z_][A-Za-z_0-9]*)`", text)}
    exported = set(dpc_jax.__all__) - {"__version__"}
    assert names == exported, (sorted(names - exported), sorted(exported - names))
    assert f"{len(exported)} names" in section
