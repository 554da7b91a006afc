"""Noise schedules, consistency-model losses and samplers: pure functions over any network."""
