from cpslam.cli import main

main()
