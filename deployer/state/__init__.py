"""State kept between runs: durable writes, the journal, device locks and snapshots."""
