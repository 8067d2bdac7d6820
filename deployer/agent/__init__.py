"""The site agent (``deployer agent``): owns a site's devices, watches them, owns windows; docs/agent.md.

The HTTP API it serves is described by ``openapi.json`` beside this file.
"""
