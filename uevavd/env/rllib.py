"""RLlib's DQN with the env's action mask (needs the ``rllib`` extra: ``pip install -e ".[rllib]"``).

RLlib ships an action-masking module for PPO (``ray.rllib.examples.rl_modules.classes.
action_masking_rlm.ActionMaskingTorchRLModule``) and none for DQN. :class:`MaskedDQNTorchRLModule`
is RLlib's default DQN module on the env's ``observation="masked"`` form
(``{"observations": flat vector, "action_mask": (7 * A,)}``): the network reads the observations,
and every Q-value a forbidden action would have is replaced, so neither the greedy action, nor
the epsilon-greedy exploration's random one (RLlib draws it among the actions whose Q-value is
not minus infinity), nor the double-DQN target's argmax takes one::

    config = (DQNConfig()
              .environment(uevavd.env.IMPORTABLE_ID, env_config={"table": TABLE_FOLDER, "actions": "flat",
                                                                 "observation": "masked"})
              .rl_module(rl_module_spec=RLModuleSpec(module_class=MaskedDQNTorchRLModule))
              .training(gamma=0.9))
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
from ray.rllib.algorithms.dqn.dqn_learner import QF_PREDS
from ray.rllib.algorithms.dqn.torch.default_dqn_torch_rl_module import DefaultDQNTorchRLModule
from ray.rllib.core.columns import Columns
from ray.rllib.utils.torch_utils import FLOAT_MIN


class MaskedDQNTorchRLModule(DefaultDQNTorchRLModule):
    """RLlib's default DQN module over ``{"observations", "action_mask"}`` observations: the
    network is built for, and reads, ``"observations"``; Q-values of forbidden actions are minus
    infinity when acting (so exploration's random actions skip them too) and RLlib's most
    negative float in training (a finite value, which the TD target's products keep finite)."""

    def __init__(self, *, observation_space: gym.Space | None = None, **kwargs: Any) -> None:
        if not isinstance(observation_space, gym.spaces.Dict) or set(observation_space) != {"observations",
                                                                                              "action_mask"}:
            raise ValueError(f"MaskedDQNTorchRLModule reads the env's observation='masked' form, a Dict of "
                             f"'observations' and 'action_mask'; got {observation_space}")
        self.observation_space_with_mask = observation_space
        self._training = False
        super().__init__(observation_space=observation_space["observations"], **kwargs)

    def setup(self) -> None:
        """RLlib's setup, for the observations; then the Dict space again, as the env gives it."""
        super().setup()
        self.observation_space = self.observation_space_with_mask

    def compute_q_values(self, batch: dict[str, Any]) -> dict[str, Any]:
        """RLlib's Q-values of the observations, forbidden actions' masked."""
        obs = batch[Columns.OBS]
        if not isinstance(obs, dict):  # already the observations alone
            return super().compute_q_values(batch)
        out = super().compute_q_values({**batch, Columns.OBS: obs["observations"]})
        forbidden = obs["action_mask"] <= 0
        fill = FLOAT_MIN if self._training else float("-inf")
        out[QF_PREDS] = out[QF_PREDS].masked_fill(forbidden, fill)
        return out

    def forward_target(self, batch: dict[str, Any]) -> dict[str, Any]:
        """The target network's Q-values, forbidden actions' at RLlib's most negative float."""
        obs = batch[Columns.OBS]
        if not isinstance(obs, dict):
            return super().forward_target(batch)
        out = super().forward_target({**batch, Columns.OBS: obs["observations"]})
        out[QF_PREDS] = out[QF_PREDS].masked_fill(obs["action_mask"] <= 0, FLOAT_MIN)
        return out

    def _forward_train(self, batch: dict[str, Any], **kwargs: Any) -> dict[str, Any]:
        self._training = True
        try:
            return super()._forward_train(batch, **kwargs)
        finally:
            self._training = False


__all__ = ["MaskedDQNTorchRLModule"]
