from perfros_bag.cli import main

main()
