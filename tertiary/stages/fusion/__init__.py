"""Fusion of the associated plots into one estimate per system target and epoch: the fusion
methods behind one registry, target confirmation, and the centralised reference."""
