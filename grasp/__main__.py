from grasp.cli import main

raise SystemExit(main())
