"""The loop pipeline: place-recognition candidates, registration, refinement, verification."""
