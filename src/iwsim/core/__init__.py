"""The foundations every other layer stands on: errors and resources, the numeric path,
checkpoints (safetensors + JSON, written atomically) and resumable runs' saved state,
metrics, configs, the one-writer lock of stores and run directories, and the generic
training loop with its distributed helpers."""
