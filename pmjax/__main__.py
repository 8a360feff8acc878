import sys

from pmjax._cli import main

sys.exit(main())
