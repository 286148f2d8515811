from visloc.cli.parser import main
import sys

sys.exit(main())
