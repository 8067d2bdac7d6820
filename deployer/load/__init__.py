"""Loading input files: safe YAML with positions, schema checks, diagnostics."""
