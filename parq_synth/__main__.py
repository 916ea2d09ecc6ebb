"""python -m parq_synth: the parq-synth command."""
import sys

from .cli import main

sys.exit(main())
