"""The report's display order and names of the shipped methods and baselines (a plugin's
entries carry their own labels; see :func:`uevavd.experiments.report_data.roles_now`)."""

from __future__ import annotations

#: Display order and names of the methods (unknown methods follow, by name).
METHOD_ORDER: tuple[str, ...] = (
    "random", "passive", "box_gate", "pose_seek", "map", "memo_map", "ibe_map", "ibe_map_sam", "ibe_map_ens",
    "ibe_map_plr", "ibe_map_reco", "ibe_map_aug", "ibe_map_aux", "ibe_map_gate", "ibe_map_stop", "ibe_map_pess",
    "ibe_map_gate_pess", "ibe_map_pose", "ibe_map_pose_gate", "ibe_map_pose_dagger", "ibe_map_pose_dagger_gate",
    "ibe_map_boxpose_gate", "ibe_map_boxpose_dagger_gate", "ibe_map_pose_pays", "ibe_map_boxpose_pays",
    "map_rule", "memo_map_rule", "ibe_map_rule", "ibe_map_boxpose_rule", "ibe_map_boxpose_rule_ens",
    "ibe_map_boxpose_rule_mirror", "ibe_map_boxpose_rule_reco", "sb3_dqn", "sb3_ppo", "departure_ceiling", "departure_ceiling2", "visibility_oracle", "oracle")
LABELS: dict[str, str] = {
    "map": "MAP",
    "memo_map": "Memo-MAP",
    "ibe_map": "IBE-MAP",
    "ibe_map_sam": "IBE-MAP (SAM masks)",
    "ibe_map_ens": "IBE-MAP (ensemble head)",
    "ibe_map_plr": "IBE-MAP (level replay)",
    "ibe_map_reco": "IBE-MAP (recognizer in the state)",
    "ibe_map_aug": "IBE-MAP (feature dropout)",
    "ibe_map_aux": "IBE-MAP (recognition probe)",
    "ibe_map_gate": "IBE-MAP (box gate in training)",
    "ibe_map_stop": "IBE-MAP (learned stop gate)",
    "ibe_map_pess": "IBE-MAP (pessimistic ensemble)",
    "ibe_map_gate_pess": "IBE-MAP (box gate + pessimistic ensemble)",
    "ibe_map_pose": "IBE-MAP (pose in the state)",
    "ibe_map_pose_gate": "IBE-MAP (pose + box gate in training)",
    "ibe_map_pose_dagger": "IBE-MAP (pose, DAgger of the visibility oracle)",
    "ibe_map_pose_dagger_gate": "IBE-MAP (pose, DAgger behind the box gate)",
    "ibe_map_boxpose_gate": "IBE-MAP (box + pose state, box gate in training)",
    "ibe_map_boxpose_dagger_gate": "IBE-MAP (box + pose state, DAgger behind the box gate)",
    "ibe_map_pose_pays": "IBE-MAP (pose, gate open where a flight pays)",
    "ibe_map_boxpose_pays": "IBE-MAP (box + pose state, gate open where a flight pays)",
    "map_rule": "MAP (pose rule where the box is hidden)",
    "memo_map_rule": "Memo-MAP (pose rule where the box is hidden)",
    "ibe_map_rule": "IBE-MAP (pose rule where the box is hidden)",
    "ibe_map_boxpose_rule": "IBE-MAP (box + pose state, pose rule where the box is hidden)",
    "ibe_map_boxpose_rule_ens": "IBE-MAP (box + pose state, pose rule where the box is hidden, context ensemble)",
    "ibe_map_boxpose_rule_mirror": "IBE-MAP (box + pose state, pose rule where the box is hidden, mirror augmentation)",
    "ibe_map_boxpose_rule_reco": "IBE-MAP (box + pose + recognizer state, pose rule where the box is hidden)",
    "random": "Random",
    "passive": "Passive",
    "box_gate": "Box gate (scripted)",
    "pose_seek": "Pose rule (scripted)",
    "departure_ceiling": "Pose rule, one exact departure (ceiling)",
    "departure_ceiling2": "Pose rule, two exact departures (ceiling)",
    "visibility_oracle": "Visibility oracle",
    "oracle": "Class-knowing oracle (upper bound)",
    "sb3_dqn": "SB3 DQN (reference)",
    "sb3_ppo": "SB3 PPO (reference)",
}
