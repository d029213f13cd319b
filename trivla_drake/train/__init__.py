"""trivla_drake.train"""
