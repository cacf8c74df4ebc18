from perfros_bag.entry import main

main()
