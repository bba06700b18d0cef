"""lasagna.priors"""
