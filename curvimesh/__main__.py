from curvimesh.cli import main

main()
