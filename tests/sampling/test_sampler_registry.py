"""Adding a sampler touches only its own code: a class with its schema (registered together; the
schema holds the defaults and the range rules, the constructor takes the validated schema) and a
variant (a YAML in conf/sampler/, here its in-memory twin in Hydra's ConfigStore). A toy sampler
registered here composes, validates, builds and trains one CPU iteration with nothing else changed."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import pytest
import torch
from hydra.core.config_store import ConfigStore

from bmimic.sampling import SAMPLERS, BinSampler, SamplerConfig, SamplerConfigError, register_sampler
from bmimic.sampling.checks import check_positive
from bmimic.sampling.config import validate_sampler_config


@dataclass
class FirstBinConfig(SamplerConfig):
    """A toy: bin 0 weighs `first_bin_weight`, every other bin 1."""

    name: str = "first_bin"
    kind: str = "first_bin"
    first_bin_weight: float = 1e6
    """Weight of bin 0 against 1 for the others (> 0)."""

    def check(self) -> None:
        check_positive("first_bin_weight", self.first_bin_weight)


@register_sampler("first_bin", FirstBinConfig)
class FirstBinSampler(BinSampler):
    def __init__(self, num_bins: int, cfg: FirstBinConfig | None = None, device: Any = "cpu") -> None:
        super().__init__(num_bins, cfg, device=device)
        self.first_bin_weight = float(self.cfg.first_bin_weight)
        w = torch.ones(num_bins, dtype=torch.float64, device=self.device)
        w[0] = self.first_bin_weight
        self._probs.copy_(w / w.sum())
        self._refresh_cdf()

    def _update(self, episodes: torch.Tensor, failures: torch.Tensor) -> None:
        pass

    def smoothed_failure(self) -> torch.Tensor:
        return torch.zeros(self.num_bins, dtype=torch.float64, device=self.device)

    def hparams(self) -> dict[str, Any]:
        return {"first_bin_weight": self.first_bin_weight}


# The variant: what conf/sampler/first_bin.yaml (defaults: [first_bin_schema, _self_]) would hold.
ConfigStore.instance().store(group="sampler", name="first_bin", node=FirstBinConfig())


def test_the_toy_is_registered_with_its_schema():
    assert SAMPLERS["first_bin"].cls is FirstBinSampler and FirstBinSampler.kind == "first_bin"
    assert "first_bin_schema.yaml" in ConfigStore.instance().repo["sampler"]
    with pytest.raises(SamplerConfigError, match="sampler.first_bin_weight must be a finite number > 0"):
        validate_sampler_config(FirstBinConfig(first_bin_weight=0.0), 30.0)

    @dataclass
    class Impostor(SamplerConfig):
        name: str = "adaptive"
        kind: str = "adaptive"

    with pytest.raises(ValueError, match="already registered"):
        register_sampler("adaptive", Impostor)(type("ImpostorSampler", (BinSampler,), {}))
    with pytest.raises(ValueError, match="kind must default to 'other'"):
        register_sampler("other", Impostor)(type("OtherSampler", (BinSampler,), {}))


def test_a_registered_sampler_trains_one_iteration(tmp_path):
    from bmimic.config import resolve_runtime
    from bmimic.runtime import seed_everything
    from bmimic.sampling.config import describe
    from bmimic.task import build_trainer, build_training
    from tests.conftest import TINY, compose

    seed_everything(0)
    cfg = compose([*TINY, "logger=none", "sampler=first_bin", "num_envs=4", "max_iterations=1", "eval.every_iters=0"])
    assert cfg.sampler.kind == "first_bin" and cfg.sampler.accounting.attribution == "start"
    resolve_runtime(cfg, "cpu")
    training = build_training(cfg, "cpu")  # validates against the motion too
    sampler, env, layout = training.sampler, training.env, training.task.layout
    assert isinstance(sampler, FirstBinSampler)
    assert env.feedback.start_bin.tolist() == [0, 0, 0, 0]  # every start drawn from the toy's P
    assert describe(cfg.sampler, layout, sampler)[0].startswith("sampler first_bin (FirstBinSampler)")
    trainer = build_trainer(training, None, tmp_path)
    trainer.learn()
    assert trainer.progress.iteration == 1
    probs = trainer.record.rows("sampler")[-1]["probability"].to_numpy()
    assert probs[0] > 0.99 and abs(probs.sum() - 1.0) < 1e-9


def test_a_sampler_that_declares_a_signal_it_does_not_learn_from_is_refused():
    from bmimic.sampling.signals import EPISODE_OUTCOMES, TRACKING_ERRORS, declared_signals

    class Deaf(BinSampler):
        signals = (EPISODE_OUTCOMES,)  # but BinSampler's own _update: the counts would be dropped

    class HalfDeaf(FirstBinSampler):
        signals = (EPISODE_OUTCOMES, TRACKING_ERRORS)  # _update it has, update_errors not

    with pytest.raises(SamplerConfigError, match="declares episode outcomes but does not implement _update"):
        declared_signals(Deaf)
    with pytest.raises(SamplerConfigError, match="declares tracking errors but does not implement update_errors"):
        declared_signals(HalfDeaf)
    assert declared_signals(SAMPLERS["egm"].cls) == SAMPLERS["egm"].cls.signals  # the built-in ones pass
    for entry in SAMPLERS.values():
        declared_signals(entry.cls)
