"""The safe-change window: from a device's first write until its change is committed or rolled back.

A change made with a soak (``--soak``) or a confirmation (``--confirm-within``) is not over at its
read-back: it is watched, then committed (the profile's ``commit`` steps, a store to non-volatile
memory) or restored from its snapshot. Everything about that window lives in this package; the
rollout (``fleet.rollout``) calls ``rollout.Window`` after each batch and at the end.

- ``held``: a device in its window (``Written``: its job and its result), the window's journal lines
- ``soak``: watching the profile's health checks
- ``finish``: sending the held commit, rolling back
- ``confirm``: waiting for ``deployer confirm``; the runs ``status`` shows as waiting or soaking
- ``rollout``: the window of a rollout, batch by batch
- ``state``: a window's state in one place (the site agent stores it; its run points to it)
- ``recover``: a window a site agent left open, ended at its next start (rolled back, or resumed)
"""
