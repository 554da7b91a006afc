"""Evaluation: metrics, videos and plots of what the models and tasks do."""
