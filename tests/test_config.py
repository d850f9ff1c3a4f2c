"""Config files and dicts → dataclasses: strict keys and types, JSON round trip, clear errors."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from dpc_jax import config as config_lib
from dpc_jax.config import ConfigError
from dpc_jax.training.train_config import TrainConfig


@dataclass(frozen=True)
class Example:
    name: str = "x"
    count: int = 1
    rate: float = 0.5
    flag: bool = False
    size: tuple[int, int] | None = None
    names: tuple[str, ...] = ()
    extra: dict = field(default_factory=dict)


def test_from_dict_converts_lists_and_ints() -> None:
    e = config_lib.from_dict(Example, {"rate": 2, "size": [3, 4], "names": ["a", "b"], "extra": {"k": 1}})
    assert e == Example(rate=2.0, size=(3, 4), names=("a", "b"), extra={"k": 1})
    assert isinstance(e.rate, float)
    assert config_lib.from_dict(Example, config_lib.to_dict(e)) == e


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"cout": 3}, "unknown key 'cout'; did you mean 'count'"),
        ({"zzz": 3}, "unknown key 'zzz'; known keys: count, extra"),
        ({"count": "3"}, "config.count: expected an integer"),
        ({"count": True}, "config.count: expected an integer"),
        ({"flag": 1}, "config.flag: expected true/false"),
        ({"size": [1, 2, 3]}, "config.size"),
        ({"names": "ab"}, "config.names: expected a sequence"),
        ({"names": ["a", 2]}, "config.names[1]: expected a string"),
    ],
)
def test_from_dict_rejects_bad_input(data: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
        config_lib.from_dict(Example, data)


def test_diff_lists_changed_keys() -> None:
    assert config_lib.diff(Example(), Example(count=2, names=("a",))) == ["count: 1 → 2", "names: [] → ['a']"]
    assert config_lib.diff(Example(), Example()) == []


def test_load_file_python_and_json(tmp_path: Path) -> None:
    (tmp_path / "a.py").write_text("CONFIG = {'count': 4, 'names': ['s']}\n")
    assert config_lib.load_file(tmp_path / "a.py", Example) == Example(count=4, names=("s",))
    (tmp_path / "b.py").write_text("CONFIG = 3\n")
    with pytest.raises(ConfigError, match="CONFIG must be a Example or a dict"):
        config_lib.load_file(tmp_path / "b.py", Example)
    (tmp_path / "c.py").write_text("OTHER = {}\n")
    with pytest.raises(ConfigError, match="defines no CONFIG"):
        config_lib.load_file(tmp_path / "c.py", Example)
    with pytest.raises(ConfigError, match="config file not found"):
        config_lib.load_file(tmp_path / "missing.py", Example)
    config_lib.save_json(tmp_path / "d.json", Example(count=7))
    assert config_lib.load_file(tmp_path / "d.json", Example) == Example(count=7)
    assert json.loads((tmp_path / "d.json").read_text())["count"] == 7
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


BASE = {"validation_sequences": ["09"], "preset": "small"}


def test_train_config_round_trip(tmp_path: Path) -> None:
    config = config_lib.from_dict(TrainConfig, {**BASE, "loss": {}, "model": {"fc_activation": "relu"}})
    config_lib.save_json(tmp_path / "config.json", config)
    assert config_lib.load_file(tmp_path / "config.json", TrainConfig) == config
    assert config.model_config().fc_activation == "relu"
    assert config.model_config().dropout == config.dropout
    (tmp_path / "run.py").write_text(
        "from dpc_jax.training.train_config import TrainConfig\n"
        "CONFIG = TrainConfig(preset='small', validation_sequences=('09',),\n"
        "                     model={'fc_activation': 'relu'})\n"
    )
    assert config_lib.load_file(tmp_path / "run.py", TrainConfig) == config


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"learing_rate": 1e-3}, "did you mean 'learning_rate'"),
        ({"method": "mono"}, "method must be one of"),
        ({"train_sequences": ["00", "09"]}, r"\['09'\] are both in train_sequences and validation_sequences"),
        ({"test_sequences": ["09"]}, "both in validation_sequences and test_sequences"),
        ({"validation_sequences": []}, "validation_sequences is empty"),
        ({"preset": "huge"}, "preset must be one of"),
        ({"model": {"widht_multiplier": 2.0}}, "unknown key 'widht_multiplier'; did you mean 'width_mul"),
        ({"model": {"dropout": 0.1}}, "model.dropout duplicates the top-level key"),
        ({"model": {"encoder_kernels": [2, 2, 2, 2, 2]}}, "model: invalid ModelConfig"),
        ({"loss": {"not_a_weight": 1.0}}, "loss: unknown key 'not_a_weight'"),
        ({"batch_size": 0}, "batch_size must be >= 1"),
        ({"learning_rate": -1.0}, "learning_rate must be > 0"),
        ({"dropout": 1.0}, r"dropout must be in \[0, 1\)"),
    ],
)
def test_train_config_rejects_inconsistent_keys(data: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        config_lib.from_dict(TrainConfig, {**BASE, **data})
