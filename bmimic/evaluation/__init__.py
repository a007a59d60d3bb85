"""Evaluating a saved policy, shared by eval, play, export and sim2sim: reopening a run folder
(`saved_run`), the per-episode, per-bin and per-segment tables (`tables`), their printed report
(`report`); the mastery rule is the run schema's (bmimic.runs.schema). The evaluator that
runs the episodes is bmimic.training.evaluator's."""
