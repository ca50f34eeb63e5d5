"""Offline tools used by the CLI, the demo and the benches: synthetic scenes (`synth`),
trajectory and reconstruction evaluation (`eval`), TSDF meshes (`mesh`), rendering a saved
map (`render`), the run report (`report`) and network namespaces for multi-host runs on one
machine (`netns`).

No agent, server, common or protocol module imports this package: it sits above them.
"""
