"""The run as the library's own object: one entry point for apply and rollback (journal, checks, report)."""
