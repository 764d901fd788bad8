"""Measuring the pipeline: accuracy against ground truth (``evaluate``) and speed
(``bench``). Nothing here runs on the robot's hot path."""
