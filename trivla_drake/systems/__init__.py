"""trivla_drake.systems"""
