"""lasagna.generators"""
