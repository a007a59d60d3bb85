"""Evaluating a saved policy, shared by eval, play, export and sim2sim: reopening a run folder
(`saved_run`), the per-episode, per-bin and per-segment tables (`tables`), their printed report
(`report`) and the mastery rule (`mastery`, torch-free: analysis uses it too). The evaluator that
runs the episodes is bmimic.training.evaluation's."""
