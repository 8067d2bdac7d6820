"""Executing a plan on one device: the session, the steps, writes, recovery and read-back."""
