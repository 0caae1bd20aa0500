import sys

from grasp.evaluate.cli import main

sys.exit(main())
