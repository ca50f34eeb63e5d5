"""What agents and server share: config, geometry, camera, datasets, evaluation."""
