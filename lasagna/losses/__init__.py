"""lasagna.losses"""
