from polarstripe.nodes.runtime.cli import main

raise SystemExit(main())
