from presim.cli import main

raise SystemExit(main())
