"""Multi-process collection in pretraining: ``collector.workers: 2`` runs TorchRL's MultiSyncCollector."""

from __future__ import annotations

import importlib
import math
import pickle
from functools import partial

import pandas as pd
import pytest
import torch
from tensordict.nn import TensorDictModule
from torchrl.envs.utils import RandomPolicy
from torchrl.modules import OneHotCategorical, ProbabilisticActor

from dcsc_torchrl.batched_envs import make_lunar_env, make_uav_env
from dcsc_torchrl.checkpoint import load_checkpoint
from dcsc_torchrl.networks import lunar_actor
from dcsc_torchrl.training import make_collector

RECIPES = {"lunarlander": "dcsc_torchrl.recipes.pretrain_a2c_lunarlander", "uav": "dcsc_torchrl.recipes.pretrain_ddpg_uav"}


@pytest.mark.parametrize("task", sorted(RECIPES))
def test_two_collector_workers_write_the_same_train_csv(task, tmp_path):
    recipe = importlib.import_module(RECIPES[task])
    recipe.main(["--quick", "--out", str(tmp_path), "collector.workers=2", "train.episodes=3"])
    log = pd.read_csv(tmp_path / "train.csv")
    assert list(log.columns) == recipe.COLUMNS
    assert log["episode"].tolist() == [1, 2, 3]
    assert log[["frames", "return", "steps"]].map(math.isfinite).all().all()
    losses = log[recipe.COLUMNS[5:]].dropna()
    assert len(losses) > 0 and losses.map(math.isfinite).all().all()
    assert load_checkpoint(tmp_path / "checkpoint.pt", task=task)["episodes"] == 3
    assert torch.get_num_threads() == 1  # the config's threads, whatever the collector's shutdown did


def test_a_two_worker_batch_has_the_single_collector_shape():
    policy = ProbabilisticActor(TensorDictModule(lunar_actor([8], 0.1), ["observation"], ["logits"]), ["logits"],
                                spec=make_lunar_env(1).full_action_spec["action"],
                                distribution_class=OneHotCategorical)
    shapes = []
    for workers in (1, 2):
        collector = make_collector(partial(make_lunar_env, random_pad=False), 4, policy, workers=workers, seed=3,
                                   frames_per_batch=20)
        batch = next(iter(collector))
        collector.shutdown()
        shapes.append(batch.shape)
        assert batch["next", "reward"].isfinite().all()
    assert shapes == [torch.Size([4, 5])] * 2


@pytest.mark.parametrize("factory", [partial(make_lunar_env, random_pad=False),
                                     partial(make_uav_env, device="cpu", collision_reward=-10.0)])
def test_env_factories_survive_pickling_to_spawned_workers(factory):
    env = pickle.loads(pickle.dumps(factory))(2)
    assert env.batch_size == torch.Size([2])
    env.close()


def test_collector_workers_must_divide_the_envs():
    policy = RandomPolicy(make_uav_env(1).full_action_spec["action"])
    with pytest.raises(ValueError, match="divide env.num_envs=3"):
        make_collector(partial(make_uav_env), 3, policy, workers=2, seed=0, frames_per_batch=6)
