from grasp.physics.cli import main

raise SystemExit(main())
