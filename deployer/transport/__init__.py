"""Transports: device URLs and the clients behind them, chosen by URL scheme."""
