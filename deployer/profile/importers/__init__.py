"""Profile importers: vendor register tables (CSV, xlsx) and SunSpec models."""
