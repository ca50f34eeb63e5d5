"""The server daemon: loops, registration, fusion, federation, pose graph."""
