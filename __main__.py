from polarstripe.tools.cli import main

raise SystemExit(main())
