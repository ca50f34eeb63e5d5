"""Offline tools used by the CLI, the demo and the benches: synthetic scenes (`synth`),
trajectory and reconstruction evaluation (`eval`), TSDF meshes (`mesh`), rendering a saved
map (`render`) and the run report (`report`).

No agent, server, common or protocol module imports this package: it sits above them.
"""
