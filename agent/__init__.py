"""The agent daemon: frame loop, tracking, mapping, keyframes."""
