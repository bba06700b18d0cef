"""lasagna.distill"""
