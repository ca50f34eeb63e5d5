"""What agents and server share at run time: config, geometry, camera, datasets, the neural
point field, registration, the bus."""
