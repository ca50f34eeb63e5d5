"""The wire contract: messages, array codec, key expressions (no torch, no zenoh)."""
