from visloc.cli import main
import sys

sys.exit(main())
