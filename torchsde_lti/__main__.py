"""``python -m torchsde_lti``: the ``torchsde-lti`` command (:mod:`torchsde_lti.cli`)."""

import sys

from torchsde_lti.cli import main

if __name__ == "__main__":
    sys.exit(main())
