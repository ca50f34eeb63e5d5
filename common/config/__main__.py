"""`python -m cpslam.common.config > docs/configuration.md` regenerates the reference page."""

import sys

from cpslam.common.config.reference import config_reference_markdown

sys.stdout.write(config_reference_markdown())
