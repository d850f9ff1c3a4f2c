"""experiments/studies/ablation.py: the rows start at the published choices and end at the demo's defaults."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from dpc_jax import config as config_lib
from dpc_jax.pipelines.demo_config import TRAINING, DemoConfig
from dpc_jax.training.train_config import REFERENCE, TrainConfig

ABLATION = Path(__file__).resolve().parents[2] / "experiments" / "studies" / "ablation.py"


def _ablation():
    spec = importlib.util.spec_from_file_location("experiment_ablation", ABLATION)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _training(values: dict) -> TrainConfig:
    fields = {**TRAINING, **values["training"], "validation_sequences": ["v"]}
    return config_lib.from_dict(TrainConfig, fields, where="test")


def test_rows_run_from_the_published_choices_to_the_demo_defaults() -> None:
    rows = _ablation().row_configs({**config_lib.to_dict(DemoConfig()), "seed": 0})
    first, last = _training(rows[0][1]), _training(rows[-1][1])
    for key, value in REFERENCE.items():
        assert getattr(first, key) == (tuple(value) if isinstance(value, list) else value), key
    published = rows[0][1]
    assert published["select"] == "gradient" and not published["acceptance"] and published["adapt_steps"] == 0
    # The last row is exactly what `dpc-jax demo` runs.
    demo = config_lib.to_dict(DemoConfig())
    assert {k: v for k, v in rows[-1][1].items() if k != "training"} == {
        k: v for k, v in demo.items() if k != "training"}
    assert last == _training({"training": demo["training"]})
