"""Run folders: training one into being, reading one back, and its videos."""
