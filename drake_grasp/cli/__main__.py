import sys

from drake_grasp.cli.main import main

sys.exit(main())
