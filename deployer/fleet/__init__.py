"""Fleets: inventories, the rollout over many devices, and the live report file."""
